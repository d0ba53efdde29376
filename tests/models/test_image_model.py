"""The centralized baseline's image model: its windows, its altitude scaling, and that it learns
from frames rendered through the JPEG uplink."""

import numpy as np
import pytest
import torch

from dronefl.config import load_scenario
from dronefl.experiments.simulate import simulate
from dronefl.logs import load_run
from dronefl.models.image import (
    FrameTransformer,
    FrameWindows,
    ImageModelConfig,
    ImageTraining,
    chronological_rows,
    evaluate_image_model,
    frame_windows,
    recorded_frame_windows,
    train_image_model,
)
from dronefl.perception.recorded_frames import render_run


def test_windows_hold_past_frames_and_the_next_position_relative_to_the_drone():
    k, n = 6, 2
    frames = np.arange(k, dtype=np.uint8)[:, None, None, None] * np.ones((1, 8, 8, 3), np.uint8)
    odometry = np.zeros((k, 12))
    odometry[:, 0] = np.arange(k)  # the drone moves 1 m east per step
    odometry[:, 2] = 25.0  # altitude, m
    odometry[:, 3] = 5.0  # vx
    visible = np.zeros((k, n), dtype=bool)
    visible[3, 0] = True
    truth = np.full((k, n, 2), 10.0)
    truth[:, 1] = np.nan  # target 2 has no label
    data = frame_windows(frames, odometry, visible, truth, drone_id=7, past_steps=3)
    assert data.index.tolist() == [[0, 1, 2], [1, 2, 3], [2, 3, 4]]  # ends t = 2, 3, 4
    assert data.frames[data.index[1]][:, 0, 0, 0].tolist() == [1, 2, 3]
    np.testing.assert_allclose(data.odometry[0, 0], [0.5, 5.0, 0.0])  # z / 50 m, vx, vy
    np.testing.assert_allclose(data.label[1, 0], [10.0 - 3.0, 10.0])  # x(t+1) - drone x(t)
    assert data.mask.tolist() == [[False, False], [True, False], [False, False]]
    assert data.drone.tolist() == [7, 7, 7]


def test_rows_split_in_time_and_keep_every_strideth_training_window():
    k, n = 12, 1
    frames = np.zeros((k, 8, 8, 3), np.uint8)
    odometry = np.zeros((k, 12))
    visible = np.ones((k, n), dtype=bool)
    visible[4] = False  # nothing to learn from in the window ending at t = 4
    data = frame_windows(frames, odometry, visible, np.zeros((k, n, 2)), 1, past_steps=2)
    train, held_out = chronological_rows(data, stride=2, train_fraction=0.5)
    ends = data.index[:, -1]
    # Steps 0-5 train (label at t + 1 <= 5), 6-11 are held out; ends run 1..10.
    assert ends[train].tolist() == [2]  # 4 has no visible target; 1 and 3 off the stride
    assert ends[held_out].tolist() == [5, 6, 7, 8, 9, 10]


def test_output_scales_with_the_altitude():
    torch.manual_seed(0)
    model = FrameTransformer(ImageModelConfig(n_targets=3, past_steps=4, frame_px=16)).eval()
    frames = torch.randint(0, 255, (2, 4, 16, 16, 3), dtype=torch.uint8)
    odometry = torch.zeros(2, 4, 3)
    odometry[:, :, 0] = 0.5
    with torch.no_grad():
        low = model(frames, odometry)
        odometry[:, -1, 0] = 1.0  # the same inputs but for the last step's altitude
        high = model(frames, odometry)
    assert low.shape == (2, 3, 2)
    assert not torch.allclose(low, high)
    with pytest.raises(ValueError, match="frame_px"):
        ImageModelConfig(n_targets=1, frame_px=8, channels=(4, 4, 4, 4))


@pytest.fixture(scope="module")
def rendered_run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("frames") / "run"
    simulate(load_scenario("case1"), environment="crop_field", duration=16.0, seed=3,
             out=folder, progress=False, plot=False)  # fmt: skip
    return folder, render_run(folder, frame_px=32, progress=False)


def test_a_run_is_rendered_through_the_jpeg_uplink_once(rendered_run):
    folder, rendered = rendered_run
    logs, truth = load_run(folder)
    assert rendered.drone_ids == (1, 2)
    assert rendered.frames.shape == (2, len(truth.t), 32, 32, 3)
    assert rendered.frames.std() > 5  # not blank
    assert (rendered.jpeg_bytes > 1000).all()  # a 640 x 640 frame is tens of KB at q90
    cached = render_run(folder, frame_px=32, progress=False)
    assert (folder / "frames_32px_q90.npz").is_file()
    np.testing.assert_array_equal(cached.frames, rendered.frames)
    np.testing.assert_array_equal(cached.jpeg_bytes, rendered.jpeg_bytes)


def test_the_image_model_learns_from_rendered_frames(rendered_run):
    folder, rendered = rendered_run
    logs, truth = load_run(folder)
    sets = recorded_frame_windows(logs, truth, rendered.frames, rendered.drone_ids, past_steps=4)
    parts = [w.subset(np.flatnonzero(w.mask.any(axis=1))) for w in sets.values()]
    data = FrameWindows.concat(parts)
    assert len(data) > 100
    torch.manual_seed(0)
    model = FrameTransformer(ImageModelConfig(n_targets=2, past_steps=4, frame_px=32))
    before = evaluate_image_model(model, data)
    stats = train_image_model(model, data, ImageTraining(epochs=12, lr=2e-3, batch_size=32))
    after = evaluate_image_model(model, data)
    assert stats.loss[-1] < 0.5 * stats.loss[0], stats.loss
    assert set(after) == {1, 2}
    assert all(after[d] < 0.5 * before[d] for d in after), (before, after)
