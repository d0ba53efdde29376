"""One simulation engine kept up while the ServerApp plays rounds on demand (the closed loop)."""

import shutil

import numpy as np
import pytest
import torch

from dronefl.fl.records import FlSettings
from dronefl.fl.server_app import initial_state
from dronefl.fl.simulation import run_session
from dronefl.logs import PseudoLabels, load_run
from dronefl.models.windows import load_drone_split


@pytest.mark.slow
def test_a_session_plays_rounds_on_new_data_with_fp16_weights(case1_run, tmp_path):
    # Prepare: each round's data in its own folder (copies of one recording); round 1's folder
    # is deleted before round 2, so a drone reading any folder but the one named fails.
    first, second = tmp_path / "round_01", tmp_path / "round_02"
    shutil.copytree(case1_run, first)
    shutil.copytree(case1_run, second)
    settings = FlSettings(str(first), str(tmp_path / "global"), rounds=1, epochs=1, stride=5,
                          weights_dtype="float16", train_fraction=1.0)  # fmt: skip
    start = initial_state(settings)

    def episode(driver):
        after_one = driver.play(start, 1, run_dir=str(first))
        shutil.rmtree(first)
        after_two = driver.play(after_one, 2, run_dir=str(second))
        return after_one, after_two, driver.history

    # Execute
    after_one, after_two, history = run_session(settings, 2, episode)

    # Assert: two global rounds, both drones trained in each on all their data (no test
    # windows, so no evaluation), weights moved each round.
    assert [h.server_round for h in history] == [1, 2]
    assert all(h.mean_test_mse is None and h.bytes_down.keys() == {"train"} for h in history)
    assert all(sorted(h.train_loss) == [1, 2] and h.rejected == () for h in history)
    assert not torch.equal(after_one["embed.weight"], start["embed.weight"])
    assert not torch.equal(after_two["embed.weight"], after_one["embed.weight"])
    # fp16 on the wire: each drone's model message is the 2-byte weights plus < 2 kB framing.
    payload = 2 * settings.layout.size
    for entry in history:
        for direction in ("down", "up"):
            per_drone = getattr(entry, f"bytes_{direction}")["train"] / 2
            assert payload < per_drone < payload + 2_000


@pytest.mark.slow
def test_an_error_in_the_episode_reaches_the_caller(case1_run, tmp_path):
    settings = FlSettings(str(case1_run), str(tmp_path / "global"), rounds=1)

    def episode(driver):
        raise ValueError("planner diverged")

    with pytest.raises(ValueError, match="planner diverged"):
        run_session(settings, 2, episode)


@pytest.mark.slow
def test_a_drone_without_labelled_windows_is_left_out_of_the_round(case1_run, tmp_path):
    # Prepare: pseudo-labels for target 1 only (what min_views = 2 leaves when only target 1
    # is seen twice); in Case 1 drone 2 follows target 2 alone, so it has no labelled window.
    data = tmp_path / "round_01"
    shutil.copytree(case1_run, data)
    logs, truth = load_run(data)
    position = truth.target_position.copy()
    position[:, truth.target_column(2)] = np.nan
    PseudoLabels(truth.t, truth.target_ids, position).save(data / "tracks.npz")
    settings = FlSettings(str(data), str(tmp_path / "global"), rounds=1, epochs=1, stride=5,
                          labels="tracks", train_fraction=1.0)  # fmt: skip
    windows = {d: len(load_drone_split(data, d, settings.windows, "tracks")[0]) for d in logs}
    assert windows[1] > 0 and windows[2] == 0, windows
    start = initial_state(settings)

    # Execute
    state, history = run_session(
        settings, 2, lambda driver: (driver.play(start, 1, run_dir=str(data)), driver.history)
    )

    # Assert: drone 1 alone trained, drone 2 left out with the reason, no error.
    (entry,) = history
    assert sorted(entry.train_loss) == [1]
    assert entry.rejected == ("drone 2: no training examples",)
    assert not torch.equal(state["embed.weight"], start["embed.weight"])
