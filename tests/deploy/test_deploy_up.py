"""`dronefl deploy up` end to end: real processes on 127.0.0.1, FL through a real SuperLink,
the per-step link over Zenoh, and nothing left running afterwards."""

import subprocess
import time

import pytest
from deploy_helpers import MARK, cli, free_port_block, survivors

from dronefl.deploy.results import DeploymentMetrics


@pytest.mark.timeout(300)
def test_deploy_up_plays_a_round_through_the_superlink_and_leaves_nothing(
    tmp_path, run_env, quick_pretrained
):
    out = tmp_path / "deploy"
    command = cli(
        "deploy", "up", "--scenario", "case1", "--duration", "12", "--fl-period", "6",
        "--epochs", "1", "--base-port", str(free_port_block()), "--out", str(out),
        "--pretrained", str(quick_pretrained),
    )  # fmt: skip
    started = time.monotonic()
    done = subprocess.run(command, env=run_env, capture_output=True, text=True, timeout=280)
    seconds = time.monotonic() - started
    assert done.returncode == 0, done.stderr[-3000:]
    assert survivors(run_env[MARK]) == []
    metrics = DeploymentMetrics.load(out / "metrics.json")
    assert metrics.engine == "deployment"
    assert metrics.processes >= 5  # world, cloud, SuperLink, 2 drones, 2 SuperNodes, ...
    (round_,) = metrics.fl_rounds  # 12 s with a round every 6 s: one round, at t = 6 s
    assert round_.t == 6.0 and round_.participants == (1, 2) and round_.missing == ()
    assert metrics.silent_steps == {1: 0, 2: 0}
    assert metrics.missing_controls == {1: 0, 2: 0}
    assert metrics.tracking.prediction_coverage > 0.5
    rate = metrics.communication.kb_per_s
    # 60 control messages of 14 B in 12 s; the weights go down twice (round + new model).
    assert rate(1, "down", "control") == pytest.approx(60 * 14 / 1000 / 12)
    assert rate(1, "down", "weights") > rate(1, "up", "weights") > 0
    names = {p.name for p in (out / "logs").glob("*.log")}
    assert {"cloud.log", "world.log", "drone-1.log", "drone-2.log"} <= names
    # The wall time is reported, not asserted (machines differ): 74 s on a quiet 2-core
    # machine, of which ~25 s are the processes' start-up and ~20 s Flower's polling.
    print(f"deploy up took {seconds:.1f} s wall")
