"""The drones' noise reports, bias correction and withheld predictions in the closed loop
(the recommended setting's ``[drone]``): reports sent beside the
predictions and counted, only the predictions of detected targets sent, the settings in
metrics.json, a replay of the episode reproducing its tracks, and a killed episode resuming
bit-identically (each drone's running estimates are in the checkpoint)."""

import json
import signal
from dataclasses import replace

import numpy as np
import pytest

from dronefl.config import load_scenario
from dronefl.experiments.loop_checkpoint import CHECKPOINT_NAME, read_loop_checkpoint
from dronefl.experiments.replay import load_episode, replay, replay_setting
from dronefl.experiments.track import NOT_IDENTITY, TrackConfig, run_episode
from dronefl.settings import Setting
from dronefl.tracking.fusion import CloudFusion

ARGS = ["--scenario", "case2", "--method", "fixed", "--set", "learning.period=7", "--duration",
        "21", "--no-animate"]  # fmt: skip
WALL_CLOCK = ("wall_seconds", "fl_seconds", "planner_ms_per_step")


def _outcome(out):
    metrics = json.loads((out / "metrics.json").read_text())
    for name in WALL_CLOCK:
        metrics.pop(name)
    metrics["config"] = {
        k: v for k, v in metrics["config"].items() if k not in NOT_IDENTITY
    }  # how it ran (a process with progress bars, or one without), not what ran
    with np.load(out / "episode.npz") as npz:
        return metrics, {k: npz[k] for k in npz.files}


@pytest.mark.slow
def test_reported_noise_flies_resumes_and_replays(quick_pretrained_case2, tmp_path, cli_process):
    pretrained = quick_pretrained_case2
    killed = tmp_path / "killed"
    argv = ["track", *ARGS, "--pretrained", str(pretrained), "--out", str(killed)]
    # Killed while writing the second checkpoint (step 70): step 35's survives.
    crash = f"write:{CHECKPOINT_NAME}@2"
    assert cli_process(argv, crash) == -signal.SIGKILL
    saved = read_loop_checkpoint(killed / CHECKPOINT_NAME)
    assert saved.step == 35 and len(saved.reporters) == 3
    assert any(np.any(r["bias"] != 0) for r in saved.reporters)
    assert cli_process([*argv, "--resume"]) == 0

    setting = Setting.load("recommended", ["learning.period=7"])
    config = TrackConfig(
        scenario=load_scenario("case2"), setting=setting, method="fixed", duration=21.0,
        pretrained=pretrained, out=tmp_path / "reference", progress=False, animate=False,
    )  # fmt: skip
    metrics = run_episode(config)
    reference = _outcome(tmp_path / "reference")
    resumed = _outcome(killed)
    assert resumed[0] == reference[0]
    for key, array in reference[1].items():
        np.testing.assert_array_equal(resumed[1][key], array, err_msg=key)

    # Sent and counted: 7 + 7 n bytes per drone and step beside 9 + 6 n of predictions.
    assert metrics.config["setting_values"]["drone"]["noise_reports"] is True
    assert metrics.config["setting_values"]["drone"]["correct_bias"] is True
    comm = metrics.communication
    for drone in (1, 2, 3):
        reports = comm.kb_per_s(drone, "up", "noise_reports")
        predictions = comm.kb_per_s(drone, "up", "predictions")
        assert 0 < reports < 1.2 * predictions
    # Every prediction is logged (Table I's error is over them all); only those of targets
    # the drone detected at that step were sent, fused, and drove the reports.
    saved = read_loop_checkpoint(tmp_path / "reference" / CHECKPOINT_NAME)
    made = np.isfinite(reference[1]["prediction"]).all(axis=-1)
    sent = reference[1]["sent"]
    detected = np.stack([r["detected"][: len(sent)] for r in saved.records], axis=1)
    assert not (sent & ~detected).any() and (made & detected == sent).all()
    assert 0 < (made & ~sent).sum() < 0.3 * made.sum()
    assert metrics.tracking.prediction_coverage == pytest.approx(made.sum() / (105 * 7))
    # A replay with the same split rebuilds the reports from the drones' records and the
    # predictions as sent (corrected in flight): the same tracks but for the half-float
    # rounding of the reports on the radio.
    episode = load_episode(tmp_path / "reference")
    assert episode.bias_corrected and episode.withheld and episode.setting == setting
    again = replay_setting(episode, episode.setting)
    assert again.measurements == saved.fuser["counters"][1]  # what was sent, nothing else
    as_flown = [t.recorded_mse for t in again.targets]
    np.testing.assert_allclose([t.fused_mse for t in again.targets], as_flown, rtol=0.02)
    # Without the reports the split is the adaptive one: other tracks.
    adaptive = replace(again.fusion.fusion, noise_split="adaptive")
    plain = replay(
        episode, CloudFusion(adaptive, replace(again.fusion.planner, noise_split="adaptive"))
    )
    assert plain.measurements == again.measurements and plain.fused_mse != again.fused_mse


def test_reported_noise_needs_the_robust_fusion():
    with pytest.raises(ValueError, match="drone.noise_reports: the paper fusion cannot use them"):
        Setting.load("recommended", ["fusion.method=paper"])
