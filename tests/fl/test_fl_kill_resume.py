"""`dronefl fl-offline` killed with SIGKILL at named points, then resumed with --resume, ends
bit-identical to an uninterrupted run: history, results (but wall-clock seconds) and final
weights. The process kills itself (``DRONEFL_CRASH_AT``, see :mod:`dronefl.io`), so each
kill lands at the same place every time; every process it started is gone afterwards."""

import json
import signal
from pathlib import Path

import numpy as np
import pytest

TINY = [
    "--scenario",
    "case1",
    "--duration",
    "40",
    "--stride",
    "5",
    "--seeds",
    "3",
    "--set",
    "training.epochs=2",
]
#: Where the runs of seed 3 live in an fl-offline folder.
SEED = "seed_3"


def fl_offline(cli_process, out: Path, *args: str, crash_at: str | None = None) -> int:
    """Run `dronefl fl-offline` in a child process (the ``cli_process`` fixture); returns its exit
    code."""
    return cli_process(["fl-offline", *TINY, "--out", str(out), *args], crash_at)


def outcome(out: Path, method: str) -> tuple[list, dict, dict[str, np.ndarray], list]:
    """History, results without wall-clock times, final weights, and the bytes of every
    message per round (apart: a message's size varies by a few bytes from run to run with the
    random node ids the engine gives the drones, which Flower writes as varints)."""
    history = json.loads((out / SEED / method / "history.json").read_text())
    results = json.loads((out / "results.json").read_text())
    sizes = [entry.pop("bytes") for entry in history]
    for block in results["methods"].values():
        block.pop("wall_seconds")
        for run in block["per_seed"]:
            run.pop("wall_seconds")
            sizes.append((run.pop("bytes_down_per_round"), run.pop("bytes_up_per_round")))
    with np.load(out / SEED / method / "checkpoint.npz") as npz:
        weights = {k: npz[k] for k in npz.files}
    return history, results, weights, sizes


def assert_identical(a: tuple, b: tuple) -> None:
    assert a[0] == b[0]  # history: every loss, MSE and rejection
    assert a[1] == b[1]
    assert a[2].keys() == b[2].keys()
    for key in a[2]:
        np.testing.assert_array_equal(a[2][key], b[2][key], err_msg=key)
    # The same messages: per round and message kind within 32 bytes of the uninterrupted run.
    flat_a, flat_b = _numbers(a[3]), _numbers(b[3])
    assert len(flat_a) == len(flat_b)
    assert all(abs(x - y) <= 8 * 4 for x, y in zip(flat_a, flat_b, strict=True))


def _numbers(tree) -> list[int]:
    if isinstance(tree, dict):
        return [n for key in sorted(tree) for n in _numbers(tree[key])]
    if isinstance(tree, list | tuple):
        return [n for item in tree for n in _numbers(item)]
    return [tree]


#: Kill points passed in turn, each in a fresh process resuming the previous one's work: a
#: kill mid-round (round 2 trained, not recorded), mid-write of round 3's checkpoint (its
#: history entry already written), mid-write of round 4's history, and mid-write of the
#: results once training is over.
CENTRALIZED_KILLS = (
    "round-end:2",
    "write:checkpoint.npz@2",
    "write:history.json@2",
    "write:results.json@1",
)


def test_centralized_run_killed_four_times_resumes_bit_identical(tmp_path, cli_process):
    method = ["--methods", "centralized", "--rounds", "4"]
    assert fl_offline(cli_process, tmp_path / "reference", *method) == 0
    reference = outcome(tmp_path / "reference", "centralized")
    assert [h["round"] for h in reference[0]] == [1, 2, 3, 4]

    out = tmp_path / "killed"
    assert fl_offline(cli_process, out, *method, crash_at=CENTRALIZED_KILLS[0]) == -signal.SIGKILL
    rounds_after_kill = [json.loads((out / SEED / "centralized/history.json").read_text())]
    for point in CENTRALIZED_KILLS[1:]:
        assert fl_offline(cli_process, out, *method, "--resume", crash_at=point) == -signal.SIGKILL
        rounds_after_kill.append(json.loads((out / SEED / "centralized/history.json").read_text()))
    # What survived each kill: round 1; rounds 1-3 in the history (round 3's checkpoint was
    # never renamed into place); rounds 1-3; all four.
    assert [[h["round"] for h in hist] for hist in rounds_after_kill] == [
        [1],
        [1, 2, 3],
        [1, 2, 3],
        [1, 2, 3, 4],
    ]
    assert not (out / "results.json").exists()
    assert fl_offline(cli_process, out, *method, "--resume") == 0
    assert_identical(outcome(out, "centralized"), reference)


@pytest.mark.slow
def test_federated_run_with_faults_killed_mid_round_resumes_bit_identical(tmp_path, cli_process):
    """FedAvg through Flower's simulation engine (in the paper's setting, as the README's
    baselines train), with drone faults in rounds 2-4 (see test_fl_dropout.py), killed after
    round 3 trained but before it was recorded."""
    method = ["--methods", "fedavg", "--rounds", "4", "--setting", "paper"]
    method += ["--faults", "2:1:raise,3:2:nan,4:1:shape"]
    assert fl_offline(cli_process, tmp_path / "reference", *method) == 0
    reference = outcome(tmp_path / "reference", "fedavg")
    assert [h["rejected"] for h in reference[0]] == [
        [],
        ["drone 1: error (drone 1: injected fault in round 2)"],
        ["drone 2: non-finite weights"],
        ["drone 1: weights with unexpected shapes"],
    ]

    out = tmp_path / "killed"
    assert fl_offline(cli_process, out, *method, crash_at="round-end:3") == -signal.SIGKILL
    assert [h["round"] for h in json.loads((out / SEED / "fedavg/history.json").read_text())] == [
        1,
        2,
    ]
    assert fl_offline(cli_process, out, *method, "--resume") == 0
    assert_identical(outcome(out, "fedavg"), reference)
