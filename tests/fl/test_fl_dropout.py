"""Drop-out end to end on Flower's simulation engine: in a round one drone's ClientApp raises,
never answers, or sends non-finite / absurd / mis-shaped weights (``faults``, see
:mod:`dronefl.fl.faults`); the round aggregates the others, the history names the drone and the
reason, and the next round includes it again. FedAvg runs the same way in
test_fl_kill_resume.py."""

import math

import pytest

from dronefl.fl import TrainingError
from dronefl.fl.checkpoint import load_checkpoint
from dronefl.fl.records import FlSettings
from dronefl.fl.simulation import run_federated


def _trained(history):
    return [sorted(int(d) for d in h.train_loss) for h in history]


def _evaluated(history):
    return [sorted(int(d) for d in h.test_mse) for h in history]


@pytest.mark.slow
def test_fedprox_rounds_survive_a_crash_and_an_absurd_update_and_one_without_any_fails(
    case1_run, tmp_path
):
    # Round 2: drone 2 crashes; round 3: drone 1 sends absurd weights; round 5: both crash, so
    # the rounds finish but the model missed a whole round, and the run fails.
    faults = "2:2:raise,3:1:absurd,5:1:raise,5:2:raise"
    settings = FlSettings(str(case1_run), str(tmp_path), method="fedprox", rounds=5, epochs=1,
                          stride=5, faults=faults)  # fmt: skip
    with pytest.raises(TrainingError, match="round 5 accepted no update") as failure:
        run_federated(settings)
    assert "drone 1: error (drone 1: injected fault in round 5)" in str(failure.value)
    assert "drone 2: error (drone 2: injected fault in round 5)" in str(failure.value)
    history = load_checkpoint(settings.checkpoint_path, settings.history_path, "fedprox").history
    assert [sorted(h.rejected) for h in history] == [  # in the order the replies came
        [],
        ["drone 2: error (drone 2: injected fault in round 2)"],
        ["drone 1: absurd weights (|w| > 10000)"],
        [],
        [
            "drone 1: error (drone 1: injected fault in round 5)",
            "drone 2: error (drone 2: injected fault in round 5)",
        ],
    ]
    assert _trained(history) == [[1, 2], [1], [2], [1, 2], []]  # back in the round after
    assert _evaluated(history) == [[1, 2]] * 5  # a rejected update does not stop evaluation
    assert all(math.isfinite(h.mean_test_mse) for h in history)


@pytest.mark.slow
def test_dronefl_round_survives_a_silent_drone_and_failed_evaluations(case1_run, tmp_path):
    # The timeout holds from the second exchange on (the first waits for the drones to start).
    settings = FlSettings(str(case1_run), str(tmp_path), method="dronefl", rounds=4, epochs=1,
                          stride=5, round_timeout=8.0,
                          faults="2:2:hang,3:1:eval-raise,4:2:eval-nan")  # fmt: skip
    history = run_federated(settings)
    assert [list(h.rejected) for h in history] == [
        [],
        ["drone 2: no reply within the round timeout"],
        ["drone 1: evaluation failed"],
        ["drone 2: non-finite test MSE"],
    ]
    assert _trained(history) == [[1, 2], [1], [1, 2], [1, 2]]
    assert _evaluated(history) == [[1, 2], [1, 2], [2], [1]]
    # The mean test MSE is over the drones that reported.
    assert history[3].mean_test_mse == history[3].test_mse[1]
