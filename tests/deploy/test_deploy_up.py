"""`dronefl deploy up` end to end: real processes on 127.0.0.1, FL through a real SuperLink,
the per-step link over Zenoh, and nothing left running afterwards."""

import subprocess
import time

import numpy as np
import pytest
from deploy_helpers import MARK, cli, free_port_block, survivors

from dronefl.config import load_scenario
from dronefl.deploy.results import DeploymentMetrics
from dronefl.experiments.pretrain import PretrainSpec
from dronefl.fl.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from dronefl.logs import PseudoLabels


@pytest.mark.timeout(400)
@pytest.mark.slow
def test_deploy_up_plays_a_round_through_the_superlink_and_leaves_nothing(
    tmp_path, run_env, quick_pretrained
):
    # Case 2's quick model: the Case 1 one (the model is the same for any scenario).
    pretrained = tmp_path / "pretrained"
    state = load_checkpoint(*_paths("case1", quick_pretrained), "dronefl").state
    save_checkpoint(*_paths("case2", pretrained), Checkpoint("dronefl", 20, state, []))
    out = tmp_path / "deploy"
    command = cli(
        "deploy", "up", "--scenario", "case2", "--env", "crop_field", "--seed", "3",
        "--duration", "30", "--fl-period", "15", "--epochs", "1", "--label-drones", "lower",
        "--base-port", str(free_port_block()), "--out", str(out), "--pretrained", str(pretrained),
    )  # fmt: skip
    started = time.monotonic()
    done = subprocess.run(command, env=run_env, capture_output=True, text=True, timeout=380)
    seconds = time.monotonic() - started
    assert done.returncode == 0, done.stderr[-3000:]
    assert survivors(run_env[MARK]) == []
    metrics = DeploymentMetrics.load(out / "metrics.json")
    assert metrics.engine == "deployment"
    assert metrics.processes >= 7  # world, cloud, SuperLink, 3 drones, 3 SuperNodes, ...
    # 30 s with a round every 15 s: one round, at t = 15 s. Drone 3 flies lowest (25 m): with
    # --label-drones lower none of its labels holds a lower view, so it sits the round out
    # (Flower: no training examples) and never loads the round's model.
    (round_,) = metrics.fl_rounds
    assert round_.t == 15.0 and round_.participants == (1, 2) and round_.missing == (3,)
    assert "drone 3: no training examples" in round_.rejected
    drones = out / "drones"
    assert np.isnan(PseudoLabels.load(drones / "drone-3" / "tracks.npz").position).all()
    assert np.isfinite(PseudoLabels.load(drones / "drone-1" / "tracks.npz").position).any()
    assert (drones / "drone-1" / "global.npz").is_file()
    assert not (drones / "drone-3" / "global.npz").exists()
    # Every drone answers in time but for a few missed 150 ms deadlines, which a loaded 2-core
    # host can cause (none on a quiet one; 1 seen once in a fresh-clone `make test`).
    assert set(metrics.silent_steps) == {1, 2, 3}
    assert all(n <= 10 for n in metrics.silent_steps.values()), metrics.silent_steps
    assert metrics.missing_controls == {1: 0, 2: 0, 3: 0}
    assert metrics.tracking.prediction_coverage > 0.5
    rate = metrics.communication.kb_per_s
    # 150 control messages of 14 B in 30 s; drones 1-2 get the weights twice (round + new
    # model), drone 3 once (the round's message only).
    assert rate(1, "down", "control") == pytest.approx(150 * 14 / 1000 / 30)
    assert rate(1, "down", "weights") > rate(3, "down", "weights") > 0
    assert rate(1, "up", "weights") > 0
    names = {p.name for p in (out / "logs").glob("*.log")}
    assert {"cloud.log", "world.log", "drone-1.log", "drone-3.log"} <= names
    # The wall time is reported, not asserted (machines differ).
    print(f"deploy up took {seconds:.1f} s wall")


def _paths(scenario: str, folder):
    settings = PretrainSpec(load_scenario(scenario), "dronefl").settings(folder)
    return settings.checkpoint_path, settings.history_path
