"""Recording a run: files, summary, determinism, and loading damaged logs."""

import json
import shutil

import numpy as np
import pytest

from dronefl.config import load_scenario
from dronefl.experiments.simulate import simulate
from dronefl.logs import GroundTruth, LogError, OnboardLog, load_run
from dronefl.serialize import to_json


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    out = tmp_path_factory.mktemp("case2")
    summary = simulate(load_scenario("case2"), duration=30.0, seed=4, out=out, progress=False)
    return out, summary


def test_run_folder_has_logs_truth_summary_and_plot(recorded):
    out, summary = recorded
    names = {p.name for p in out.iterdir()}
    assert {
        "drone_1.npz",
        "drone_2.npz",
        "drone_3.npz",
        "ground_truth.npz",
        "summary.json",
        "topdown.png",
    } <= names
    assert not [n for n in names if n.endswith(".tmp")]
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk["sim_seconds"] == pytest.approx(30.0)
    assert on_disk["wall_seconds"] > 0
    assert [d["drone_id"] for d in on_disk["drones"]] == [1, 2, 3]
    assert on_disk == to_json(summary)


def test_logs_hold_boxes_and_odometry_never_images(recorded):
    out, summary = recorded
    logs, truth = load_run(out)
    log = logs[2]
    assert log.t.shape == (150,) and log.odometry.shape == (150, 12)
    assert log.boxes.shape == (150, 3, 4)
    assert log.assigned_ids == (1, 2)
    assert np.isnan(log.boxes[~log.detected]).all()
    assert ((log.boxes[log.detected] >= 0) & (log.boxes[log.detected] <= 1)).all()
    assert truth.target_position.shape == (150, 3, 2)
    # The summary's detection rate is the detection mask's mean over the assigned targets.
    assert summary.drones[1].detection_rate == pytest.approx(log.detected[:, log.assigned].mean())


def test_odometry_in_the_log_is_the_drone_truth_plus_small_noise(recorded):
    out, _ = recorded
    logs, truth = load_run(out)
    err = logs[1].odometry[:, :2] - truth.drone_position[:, 0]
    assert np.abs(err).max() < 0.3 and np.abs(err).mean() > 0.0


def test_same_seed_gives_identical_logs(tmp_path):
    scenario = load_scenario("case1")
    for name in ("a", "b"):
        simulate(scenario, duration=10.0, seed=7, out=tmp_path / name, progress=False, plot=False)
    for file in ("drone_1.npz", "drone_2.npz", "ground_truth.npz"):
        with np.load(tmp_path / "a" / file) as a, np.load(tmp_path / "b" / file) as b:
            for key in a.files:
                equal_nan = a[key].dtype.kind == "f"
                assert np.array_equal(a[key], b[key], equal_nan=equal_nan), (file, key)


def test_truncated_log_gives_a_clear_error_naming_the_file(recorded, tmp_path):
    out, _ = recorded
    damaged = tmp_path / "drone_1.npz"
    data = (out / "drone_1.npz").read_bytes()
    damaged.write_bytes(data[: len(data) // 2])
    with pytest.raises(LogError, match=f"{damaged}: truncated or corrupt"):
        OnboardLog.load(damaged)


def test_garbage_and_wrong_format_files_are_rejected(recorded, tmp_path):
    out, _ = recorded
    garbage = tmp_path / "drone_9.npz"
    garbage.write_bytes(b"\x00not a zip file at all")
    with pytest.raises(LogError, match="truncated or corrupt"):
        OnboardLog.load(garbage)
    swapped = tmp_path / "swapped.npz"
    shutil.copy(out / "ground_truth.npz", swapped)
    with pytest.raises(LogError, match="not a dronefl.onboard_log file"):
        OnboardLog.load(swapped)
    with pytest.raises(LogError, match="no such log file"):
        GroundTruth.load(tmp_path / "missing.npz")


def test_inconsistent_shapes_are_rejected(recorded, tmp_path):
    out, _ = recorded
    log = OnboardLog.load(out / "drone_1.npz")
    bad = tmp_path / "drone_1.npz"
    OnboardLog(
        log.drone_id,
        log.altitude,
        log.t,
        log.odometry[:-1],
        log.target_ids,
        log.assigned,
        log.boxes,
        log.detected,
        log.confidence,
        log.meta,
    ).save(bad)
    with pytest.raises(LogError, match="'odometry' has shape"):
        OnboardLog.load(bad)
