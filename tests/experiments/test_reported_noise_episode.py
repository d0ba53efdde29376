"""The drones' noise reports, bias correction and withheld predictions in the closed loop
(``--noise-split reported --correct-bias --detected-only``): reports sent beside the
predictions and counted, only the predictions of detected targets sent, the settings in
metrics.json, a replay of the episode reproducing its tracks, and a killed episode resuming
bit-identically (each drone's running estimates are in the checkpoint)."""

import json
import pickle
import signal

import numpy as np
import pytest

from dronefl.config import load_scenario
from dronefl.experiments.loop_checkpoint import CHECKPOINT_NAME
from dronefl.experiments.replay import flown_config, load_episode, replay, replay_config
from dronefl.experiments.track import NOT_SETTINGS, TrackConfig, run_episode

ARGS = ["--setting", "ours", "--scenario", "case2", "--method", "fixed", "--noise-split",
        "reported", "--correct-bias", "--detected-only", "--duration", "21", "--fl-period", "7",
        "--no-animate"]  # fmt: skip
WALL_CLOCK = ("wall_seconds", "fl_seconds", "planner_ms_per_step")


def _outcome(out):
    metrics = json.loads((out / "metrics.json").read_text())
    for name in WALL_CLOCK:
        metrics.pop(name)
    metrics["config"] = {
        k: v for k, v in metrics["config"].items() if k not in NOT_SETTINGS
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
    with (killed / CHECKPOINT_NAME).open("rb") as handle:
        saved = pickle.load(handle)
    assert saved.step == 35 and len(saved.reporters) == 3
    assert any(np.any(r.residual.bias() != 0) for r in saved.reporters)
    assert cli_process([*argv, "--resume"]) == 0

    config = TrackConfig(
        scenario=load_scenario("case2"), method="fixed", noise_split="reported", duration=21.0,
        fl_period=7.0, pretrained=pretrained, out=tmp_path / "reference", progress=False,
        animate=False, correct_bias=True, detected_only=True,
    )  # fmt: skip
    metrics = run_episode(config)
    reference = _outcome(tmp_path / "reference")
    resumed = _outcome(killed)
    assert resumed[0] == reference[0]
    for key, array in reference[1].items():
        np.testing.assert_array_equal(resumed[1][key], array, err_msg=key)

    # Sent and counted: 7 + 7 n bytes per drone and step beside 9 + 6 n of predictions.
    assert json.loads(metrics.config["fusion_config"])["noise_split"] == "reported"
    assert metrics.config["correct_bias"] is True
    comm = metrics.communication
    for drone in (1, 2, 3):
        reports = comm.kb_per_s(drone, "up", "noise_reports")
        predictions = comm.kb_per_s(drone, "up", "predictions")
        assert 0 < reports < 1.2 * predictions
    # Every prediction is logged (Table I's error is over them all); only those of targets
    # the drone detected at that step were sent, fused, and drove the reports.
    assert metrics.config["detected_only"] is True
    with (tmp_path / "reference" / CHECKPOINT_NAME).open("rb") as handle:
        saved = pickle.load(handle)
    made = np.isfinite(reference[1]["prediction"]).all(axis=-1)
    sent = reference[1]["sent"]
    detected = np.stack([r.detected[: len(sent)] for r in saved.records], axis=1)
    assert not (sent & ~detected).any() and (made & detected == sent).all()
    assert 0 < (made & ~sent).sum() < 0.3 * made.sum()
    assert metrics.tracking.prediction_coverage == pytest.approx(made.sum() / (105 * 7))
    # A replay with the same split rebuilds the reports from the drones' records and the
    # predictions as sent (corrected in flight): the same tracks but for the half-float
    # rounding of the reports on the radio.
    episode = load_episode(tmp_path / "reference")
    assert episode.bias_corrected
    again = replay(episode, replay_config(episode.scenario, noise_split="reported"))
    assert again.measurements == saved.fuser.measurements  # what was sent, nothing else
    as_flown = [t.recorded_mse for t in again.targets]
    np.testing.assert_allclose([t.fused_mse for t in again.targets], as_flown, rtol=0.02)
    # `replay --as-flown` reads those settings from metrics.json instead of the options.
    assert episode.detected_only and episode.flown_fusion.noise_split == "reported"
    flown = replay(episode, flown_config(episode), detected_only=True)
    assert flown.measurements == again.measurements
    np.testing.assert_allclose([t.fused_mse for t in flown.targets], as_flown, rtol=0.02)


def test_reported_noise_needs_the_robust_fusion(tmp_path):
    with pytest.raises(ValueError, match="--noise-split reported: needs --fusion robust"):
        TrackConfig(
            scenario=load_scenario("case2"), noise_split="reported", fusion="paper", out=tmp_path
        )
    with pytest.raises(ValueError, match="--noise-split"):
        TrackConfig(scenario=load_scenario("case2"), noise_split="oracle", out=tmp_path)


def test_episodes_flown_before_the_option_keep_their_settings(tmp_path):
    # An adaptive episode's settings are those written before --noise-split existed, so
    # table1 and --resume still reuse its results; a reported one's name the split.
    adaptive = TrackConfig(scenario=load_scenario("case2"), out=tmp_path).settings()
    assert "noise_split" not in adaptive
    assert "noise_split" not in json.loads(adaptive["fusion_config"])
    reported = TrackConfig(
        scenario=load_scenario("case2"), noise_split="reported", out=tmp_path
    ).settings()
    assert reported["noise_split"] == "reported"
    assert json.loads(reported["fusion_config"])["noise_split"] == "reported"
    # Likewise the bias correction: named only when on.
    assert "correct_bias" not in adaptive
    corrected = TrackConfig(scenario=load_scenario("case2"), correct_bias=True, out=tmp_path)
    assert corrected.settings()["correct_bias"] is True
    # And the withheld predictions.
    assert "detected_only" not in adaptive
    withheld = TrackConfig(scenario=load_scenario("case2"), detected_only=True, out=tmp_path)
    assert withheld.settings()["detected_only"] is True
    # And the net reports, which need reports.
    assert "net_reports" not in reported
    net = TrackConfig(
        scenario=load_scenario("case2"), noise_split="reported", net_reports=True, out=tmp_path
    )
    assert net.settings()["net_reports"] is True
    with pytest.raises(ValueError, match="--net-reports: needs --noise-split reported"):
        TrackConfig(scenario=load_scenario("case2"), net_reports=True, out=tmp_path)
