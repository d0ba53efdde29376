"""`dronefl deploy up` end to end and its faults: real processes on 127.0.0.1, FL through a
real SuperLink, the per-step link over Zenoh; a drone killed mid-episode never stops it, a
restarted drone rejoins, and nothing is left running afterwards."""

import os
import signal
import subprocess

import numpy as np
import psutil
import pytest
from deploy_helpers import MARK, cli, free_port_block, survivors, wait_for_line

from dronefl.config import load_scenario
from dronefl.deploy.clientapp import load_model
from dronefl.deploy.results import DeploymentMetrics
from dronefl.experiments.replay import load_episode, replay_setting
from dronefl.experiments.track import TrackConfig, run_episode
from dronefl.fl.checkpoint import load_checkpoint
from dronefl.logs import PseudoLabels
from dronefl.settings import Setting
from dronefl.tracking.fusion import TEMPORAL_KERNEL


def _drone_process(launcher: subprocess.Popen, drone_id: int) -> psutil.Process | None:
    for child in psutil.Process(launcher.pid).children():
        line = child.cmdline()
        if "drone" in line and line[line.index("--id") + 1] == str(drone_id):
            return child
    return None


#: The deployment's setting: the recommended one with a round every 25 s.
SETTING = ["learning.period=25"]


def _equal_steps(a: np.ndarray, b: np.ndarray) -> int:
    """Leading steps (first axis) of ``a`` and ``b`` equal to the bit, NaN equal to NaN."""
    same = (a == b) | (np.isnan(a) & np.isnan(b))
    same = same.reshape(len(a), -1).all(axis=1)
    return len(a) if same.all() else int(np.argmin(same))


@pytest.mark.timeout(600)
@pytest.mark.slow
def test_deploy_up_rides_out_a_killed_drone_and_leaves_nothing(
    tmp_path, run_env, quick_pretrained_case2
):
    out = tmp_path / "deploy"
    command = cli(
        "deploy", "up", "--scenario", "case2", "--env", "crop_field", "--seed", "3",
        "--duration", "60", *(a for o in SETTING for a in ("--set", o)),
        "--base-port", str(free_port_block()),
        "--out", str(out),
        "--pretrained", str(quick_pretrained_case2), "--restart-drones",
    )  # fmt: skip
    said = tmp_path / "launcher.out"
    with said.open("w") as output:
        launcher = subprocess.Popen(command, env=run_env, stdout=output, stderr=subprocess.STDOUT)
    try:
        # Killed once the launcher has seen every process up (a drone dying before that is a
        # failed start, not a fault to ride out) and the world has done 50 steps (every track
        # exists), well before the first round at step 125; a restart (Python, torch, Zenoh, a
        # SuperNode) takes seconds, the 75 steps left take about one.
        wait_for_line(said, "deploy: all up", launcher, 300)
        wait_for_line(out / "logs" / "world.log", "step 50/", launcher, 300)
        victim = _drone_process(launcher, 2)
        assert victim is not None, said.read_text()
        os.killpg(victim.pid, signal.SIGKILL)  # the drone process and its SuperNode
        launcher.wait(timeout=500)
    finally:
        if launcher.poll() is None:
            launcher.send_signal(signal.SIGINT)
            launcher.wait(60)
    stdout = said.read_text()
    assert launcher.returncode == 0, stdout[-3000:]
    assert survivors(run_env[MARK]) == []
    metrics = DeploymentMetrics.load(out / "metrics.json")
    assert metrics.engine == "deployment"
    setting = Setting.load("recommended", SETTING)
    assert Setting.load(str(out / "setting.toml")) == setting  # every process read it

    # The same drone and cloud classes as `dronefl track`: before the kill the deployment
    # flies the same steps as the closed loop in one process, to the bit.
    track = TrackConfig(
        load_scenario("case2"), tmp_path / "track", setting, method="dronefl", seed=3,
        duration=10.0, environment="crop_field", pretrained=quick_pretrained_case2,
        progress=False, animate=False,
    )  # fmt: skip
    run_episode(track)
    with (
        np.load(out / "episode.npz") as deployed,
        np.load(tmp_path / "track" / "episode.npz") as one,
    ):
        received = np.where(one["sent"][..., None], one["prediction"], np.nan)
        assert _equal_steps(deployed["prediction"][:40], received[:40]) == 40
        for key in ("track_position", "trace", "cost"):
            assert _equal_steps(deployed[key][:40], one[key][:40]) == 40, key

    # The planner flew on a second, q = 30 filter with the temporal kernel, the labels' filter
    # the fusion's own, with the drones' noise reports: the replay of what the cloud received
    # (predictions and reports), with the setting the deployment records, gives back its
    # tracks; one filter, the adaptive split or no kernel does not.
    episode = load_episode(out)
    assert episode.setting == setting and episode.received_reports is not None
    assert np.isfinite(episode.received_reports).any()
    flown = replay_setting(episode, episode.setting)
    assert flown.fusion.planner.acceleration_psd == 30.0
    assert flown.fusion.fusion.temporal_kernel == TEMPORAL_KERNEL
    # (Where some drone sent the target at each of the last 5 steps the output is the
    # kernel's whatever the filter's q: one filter then moves the tracks less.)
    others = (
        (setting.override(["fusion.random_walk_planner_psd=none"]), 1e-6),
        (setting.override(["drone.noise_reports=false"]), 1e-3),
        (setting.override(["fusion.temporal_kernel=false"]), 1e-3),
    )
    for other, apart in others:
        changed = replay_setting(episode, other)
        for target, moved in zip(flown.targets, changed.targets, strict=True):
            assert target.fused_mse == pytest.approx(target.recorded_mse, rel=1e-9, abs=1e-12)
            assert moved.fused_mse != pytest.approx(target.recorded_mse, rel=apart)
    assert metrics.processes >= 7  # world, cloud, SuperLink, 3 drones, 3 SuperNodes, ...

    # Rounds at steps 125 and 250 (t = 25 s, 50 s): the episode went on. Drone 2 was dead in
    # round 1; restarted, it rejoined round 2.
    rounds = {r.round: r for r in metrics.fl_rounds}
    assert sorted(rounds) == [1, 2] and rounds[1].t == 25.0
    assert rounds[1].participants == (1, 3) and rounds[1].missing == (2,), rounds[1]
    assert rounds[2].participants == (1, 2, 3) and rounds[2].missing == (), rounds[2]
    assert metrics.missed_rounds == {1: (), 2: (1,), 3: ()}
    drones = out / "drones"
    for d in (1, 2, 3):
        assert np.isfinite(PseudoLabels.load(drones / f"drone-{d}" / "tracks.npz").position).any()
    # The recommended setting's model reached every process: the drones fly and install the
    # model that reads box sizes in proportion to the ground, and SCAFFOLD's control variates
    # went round: each drone that trained keeps its c_i on its disk, the cloud keeps c (the
    # mean of the c_i) in its checkpoint.
    installed = load_model(drones / "drone-1" / "global.npz")
    assert installed.server_round == 2 and installed.model.box_size == "metric"
    assert load_model(out / "model" / "pretrained.npz").model == installed.model
    with np.load(drones / "drone-1" / "control" / "drone_1_round_2.npz") as control:
        assert any(np.abs(control[k]).max() > 0 for k in control.files)
    cloud_fl = out / "cloud" / "fl" / "global"
    checkpoint = load_checkpoint(cloud_fl / "checkpoint.npz", cloud_fl / "history.json", "dronefl")
    assert checkpoint.server_round == 2 and checkpoint.control is not None
    assert any(bool(v.abs().max() > 0) for v in checkpoint.control.values())

    # One gap: from the kill (after step 50) to the restarted drone's first message, which
    # comes after round 1 (played after step 124, the drone dead then) and before round 2.
    with np.load(out / "cloud" / "cloud.npz") as cloud:
        silent = cloud["silent"][:, load_scenario("case2").drone_ids.index(2)]
    gap = np.flatnonzero(silent)
    assert gap.size and (np.diff(gap) == 1).all(), gap
    assert gap[0] >= 50 and 124 <= gap[-1] < 249, (gap[0], gap[-1])
    assert metrics.silent_steps[2] == gap.size
    # The live drones may miss a 150 ms deadline now and then on a loaded machine, no more
    # (none on a quiet one).
    assert metrics.silent_steps[1] <= 25 and metrics.silent_steps[3] <= 25, metrics.silent_steps
    assert metrics.missing_controls[1] == 0 and metrics.missing_controls[3] == 0
    # While drone 2 was gone the cloud kept every track (never dropped once all existed).
    with np.load(out / "episode.npz") as saved:
        tracked = np.isfinite(saved["track_position"]).all(axis=(1, 2))
    assert tracked[gap[0]] and tracked[np.argmax(tracked) :].all()
    assert metrics.tracking.prediction_coverage > 0.5

    # Restarted (its autopilot held position meanwhile), it talks to the cloud again,
    # trains in round 2 through its new SuperNode and loads that model.
    assert "drone 2 restarted" in stdout
    restarted = (out / "logs" / "drone-2-restart1.log").read_text()
    assert "model of round 2 loaded" in restarted
    rate = metrics.communication.kb_per_s
    # 300 control messages of 14 B in 60 s; drones 1 and 3 get the weights four times (two
    # rounds, two new models), drone 2 twice (round 2 and its model). (To a few bytes: each
    # message names its SuperNode, whose random 64-bit id takes 9 or 10 bytes.)
    assert rate(1, "down", "control") == pytest.approx(300 * 14 / 1000 / 60)
    weights = {d: rate(d, "down", "weights") for d in (1, 2, 3)}
    assert weights[1] == pytest.approx(weights[3], abs=10 / 1000 / 60)
    assert weights[1] > weights[2] > 0
    assert rate(1, "up", "weights") > 0
    names = {p.name for p in (out / "logs").glob("*.log")}
    assert {"cloud.log", "world.log", "drone-1.log", "drone-3.log"} <= names
