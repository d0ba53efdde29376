"""`dronefl track` killed with SIGKILL, then resumed with --resume, ends bit-identical to an
uninterrupted episode: metrics.json (but the wall-clock times), every array of episode.npz, the
FL round history and the final global weights. The process kills itself (``DRONEFL_CRASH_AT``,
see :mod:`dronefl.io`), so each kill lands at the same place every time; every process it
started (Ray's included) is gone afterwards.

The episode: DroneFL on Case 1, 21 s = 105 steps, an FL round after steps 35 and 70, a
checkpoint after steps 35, 70 and 105.
"""

import json
import signal
from pathlib import Path

import numpy as np
import pytest
from cli_child import run_cli

from dronefl.experiments.loop_checkpoint import CHECKPOINT_NAME, read_loop_checkpoint

DURATION = 21.0
#: Every drone learns every label, so Case 1 (one drone per target) has rounds.
TRACK = ["track", "--set", "learning.label_drones=all", "--scenario", "case1", "--duration",
         str(DURATION), "--set", "learning.period=7", "--no-animate"]  # fmt: skip
#: metrics.json fields that are wall-clock times (each FL round's ``seconds`` too).
WALL_CLOCK = ("wall_seconds", "fl_seconds", "planner_ms_per_step")
#: How much a round's message may differ in size from the uninterrupted run's, B: the engine
#: gives the drones random node ids, which Flower writes as varints (as between any two runs).
MESSAGE_SLACK = 32


def track(cli_process, out: Path, pretrained: Path, *args: str, crash_at: str | None = None):
    """`dronefl track` of the test's episode in a child process; returns its exit code."""
    argv = [*TRACK, "--pretrained", str(pretrained), "--out", str(out), *args]
    return cli_process(argv, crash_at)


def checkpoint_step(out: Path) -> int:
    """The step the episode checkpoint in ``out`` resumes from."""
    return read_loop_checkpoint(out / CHECKPOINT_NAME).step


def outcome(out: Path) -> tuple[dict, dict, list, dict, list[int]]:
    """metrics.json without wall-clock times and weight bytes, episode.npz, the round history
    without bytes, the final weights (the server's global model, the drones' predictor), and
    every weight byte count (kept apart: see :data:`MESSAGE_SLACK`)."""
    metrics = json.loads((out / "metrics.json").read_text())
    for name in WALL_CLOCK:
        metrics.pop(name)
    sizes = []
    for entry in metrics["fl_rounds"]:
        entry.pop("seconds")
        sizes += [*entry.pop("weight_bytes_down").values(), *entry.pop("weight_bytes_up").values()]
    rates = metrics["communication"].pop("rates")
    metrics["communication"] = [r for r in rates if r["kind"] != "weights"]
    sizes += [round(1000 * r["kb_per_s"] * DURATION) for r in rates if r["kind"] == "weights"]
    config = metrics.pop("config")
    metrics["config"] = {k: v for k, v in config.items() if k != "out"}
    with np.load(out / "episode.npz") as npz:
        episode = {k: npz[k] for k in npz.files}
    history = json.loads((out / "fl" / "global" / "history.json").read_text())
    for entry in history:
        for way in ("down", "up"):
            sizes += entry["bytes"][way].values()
        entry.pop("bytes")
    with np.load(out / "fl" / "global" / "checkpoint.npz") as npz:
        weights = {k: npz[k] for k in npz.files}
    predictors = read_loop_checkpoint(out / CHECKPOINT_NAME).predictors  # the drones', at the end
    for drone, state in predictors.items():
        weights |= {f"predictor {drone}:{k}": v for k, v in state.items()}
    return metrics, episode, history, weights, sizes


def assert_identical(a: tuple, b: tuple) -> None:
    assert a[0] == b[0]  # every metric, loss, count and setting
    for parts in (1, 3):  # the episode's arrays, the final weights
        assert a[parts].keys() == b[parts].keys()
        for key in a[parts]:
            np.testing.assert_array_equal(a[parts][key], b[parts][key], err_msg=key)
    assert a[2] == b[2]  # the round history: every loss and rejection
    assert len(a[4]) == len(b[4])
    assert all(abs(x - y) <= MESSAGE_SLACK for x, y in zip(a[4], b[4], strict=True))


@pytest.mark.slow
def test_episode_killed_mid_round_and_mid_checkpoint_resumes_bit_identical(
    tmp_path, quick_pretrained, cli_process, capsys
):
    out = tmp_path / "killed"
    # Killed mid-round: round 2 trained, not recorded; step 35's checkpoint (after round 1)
    # survives.
    assert track(cli_process, out, quick_pretrained, crash_at="round-end:2") == -signal.SIGKILL
    assert checkpoint_step(out) == 35 and not (out / "metrics.json").exists()
    # Resumed (round 2 played again in a new Flower session) and killed mid-write of the last
    # checkpoint: step 70's is still whole.
    kill = f"write:{CHECKPOINT_NAME}@2"
    assert track(cli_process, out, quick_pretrained, "--resume", crash_at=kill) == -signal.SIGKILL
    assert checkpoint_step(out) == 70 and not (out / "metrics.json").exists()
    assert track(cli_process, out, quick_pretrained, "--resume") == 0
    assert checkpoint_step(out) == 105
    # The uninterrupted episode (run last, while the killed runs' Ray agents wind down).
    assert track(cli_process, tmp_path / "reference", quick_pretrained) == 0
    reference = outcome(tmp_path / "reference")
    assert [entry["round"] for entry in reference[2]] == [1, 2]
    assert_identical(outcome(out), reference)

    # A finished episode is reused: a rerun would be killed at its first checkpoint.
    finished = (out / "metrics.json").read_bytes()
    first = f"write:{CHECKPOINT_NAME}"
    assert track(cli_process, out, quick_pretrained, "--resume", crash_at=first) == 0
    assert (out / "metrics.json").read_bytes() == finished
    # Another episode's results, or checkpoint: one line naming the file and the setting,
    # before any work.
    argv = [*TRACK, "--pretrained", str(quick_pretrained), "--out", str(out), "--resume"]
    code, err = run_cli(capsys, *argv, "--set", "learning.period=15")
    assert code == 2 and "metrics.json" in err and "setting is" in err
    (out / "metrics.json").unlink()
    code, err = run_cli(capsys, *argv, "--seed", "1")
    assert code == 2 and CHECKPOINT_NAME in err and "seed is 0 there, 1 here" in err
