"""dronefl replay: a tiny hand-made episode re-fused with the paper's and the robust method;
per-drone errors by hand; JSON and markdown written; bad folders give one-line errors; the
drones' noise reports rebuilt from their records."""

import json
from dataclasses import fields, replace

import numpy as np
import pytest
from typer.testing import CliRunner

from dronefl.cli import app
from dronefl.config import load_scenario
from dronefl.experiments.loop_checkpoint import (
    CHECKPOINT_NAME,
    LoopCheckpoint,
    save_loop_checkpoint,
)
from dronefl.experiments.replay import (
    EpisodeError,
    drone_reports,
    format_result,
    load_episode,
    oracle_weighting_mse,
    replay,
    replay_setting,
    temporal_oracle,
)
from dronefl.models.online import OnboardRecord
from dronefl.results.episode import REPORTS_NAME
from dronefl.settings import Setting
from dronefl.sim.camera import PinholeCamera
from dronefl.tracking import Fuser, PositionMeasurement
from dronefl.tracking.fusion import TEMPORAL_KERNEL, CloudFusion, cloud_fusion

DT = 0.2  # s, the scenarios' step


def _episode(folder, n_steps=150, seed=0):
    """Case 2 (3 drones, 3 targets): targets drive east at 0.5 m/s; drone 1 predicts every
    target with 0.5 m noise, drone 2 target 2 with 0.2 m noise, drone 3 nothing."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_steps + 1) * DT
    truth = np.zeros((n_steps + 1, 3, 2))
    for j in range(3):
        truth[:, j, 0] = 10.0 * j + 0.5 * t
        truth[:, j, 1] = 5.0 * j
    prediction = np.full((n_steps, 3, 3, 2), np.nan)
    prediction[:, 0] = truth[1:] + rng.normal(0, 0.5, (n_steps, 3, 2))
    prediction[:, 1, 1] = truth[1:, 1] + rng.normal(0, 0.2, (n_steps, 2))
    folder.mkdir(parents=True, exist_ok=True)
    np.savez(
        folder / "episode.npz",
        t=t,
        target_position=truth,
        track_position=truth + 0.1,
        prediction=prediction,
        drone_position=np.zeros((n_steps + 1, 3, 2)),
    )
    _record_setting(folder, None)
    return prediction, truth


def _record_setting(folder, setting):
    """Write the episode's ``metrics.json`` naming Case 2 and, unless ``None``, ``setting``."""
    config = {"scenario": "case2", "seed": 0}
    if setting is not None:
        config |= {"setting_name": setting.name, "setting_values": setting.to_dict()}
    (folder / "metrics.json").write_text(json.dumps({"config": config}))


def _filters(name="recommended", reported=False, **fusion) -> CloudFusion:
    """Case 2's filters as the setting ``name`` (with ``fusion`` fields changed) makes them."""
    setting = Setting.load(name).with_values(fusion=fusion) if fusion else Setting.load(name)
    return cloud_fusion(setting.fusion, reported, load_scenario("case2"))


def _one_filter(method="robust", **config) -> CloudFusion:
    """Case 2's fusion filter alone (the planner on it), ``config`` fields changed."""
    fusion = _filters("paper", method=method).fusion
    return CloudFusion(replace(fusion, **config))


def test_replay_reports_each_drone_beside_the_fused_track(tmp_path):
    prediction, truth = _episode(tmp_path / "ep")
    episode = load_episode(tmp_path / "ep")
    result = replay(episode, _one_filter("paper"))
    target2 = result.targets[1]
    # Per-drone errors by hand: prediction at k against the truth at k + 1.
    by_hand = {i + 1: np.mean(((prediction[:, i, 1] - truth[1:, 1]) ** 2).sum(-1)) for i in (0, 1)}
    assert [d.drone_id for d in target2.drones] == [1, 2]
    for d in target2.drones:
        assert d.mse == pytest.approx(by_hand[d.drone_id], rel=1e-12)
        assert d.n == 150
    assert target2.recorded_mse == pytest.approx(0.02, rel=1e-9)  # (0.1^2 + 0.1^2)
    # The same stream through a Fuser by hand gives the same filtered track error.
    fuser = Fuser(episode.scenario.target_ids, episode.scenario.drone_ids, result.fusion.tracks)
    errors = []
    for k in range(150):
        ms = [
            PositionMeasurement(i + 1, j + 1, prediction[k, i, j])
            for i in range(3)
            for j in range(3)
            if np.isfinite(prediction[k, i, j]).all()
        ]
        errors.append(np.sum((fuser.update((k + 1) * DT, ms)[2].position - truth[k + 1, 1]) ** 2))
    assert target2.fused_mse == pytest.approx(np.mean(errors), rel=1e-9)
    assert result.measurements == 600 - 4  # step 0's 4 measurements start the 3 tracks
    # Fusion of a 0.2 m and a 0.5 m drone with a CV model beats the better drone.
    assert target2.fused_over_best < 0.9
    # The fixed-weights oracle of two independent drones beats the better one, and no
    # single-drone target gains from it.
    assert target2.oracle_over_best < 0.9
    assert result.targets[0].oracle_over_best == pytest.approx(1.0, rel=1e-9)
    assert result.label_mse < result.fused_mse  # smoothed labels beat the filtered track


def test_oracle_weighting_by_hand():
    # Two drones with independent errors of variance 1 and 4 (per axis): the inverse-variance
    # weights (0.8, 0.2) reach 1 / (1 + 1/4) = 0.8 of the better drone's error.
    rng = np.random.default_rng(3)
    k = 20_000
    errors = np.stack([rng.normal(0, 1, (k, 2)), rng.normal(0, 2, (k, 2))], axis=1)
    seen = np.ones((k, 2), bool)
    best_mse = (errors[:, 0] ** 2).sum(-1).mean()
    assert oracle_weighting_mse(errors, seen, 0) / best_mse == pytest.approx(0.8, abs=0.01)
    # Errors shared by both drones cannot be weighted away: the oracle is the better drone.
    shared = np.repeat(errors[:, :1], 2, axis=1)
    assert oracle_weighting_mse(shared, seen, 0) == pytest.approx(best_mse, rel=1e-9)
    # Correlation 0.75 with variances 1 and 4: the better drone's std ratio 0.5 < 0.75, so the
    # best weights put a negative weight on the worse drone; the minimum is
    # s1² s2² (1 - rho²) / (s1² + s2² - 2 rho s1 s2) = 4 * 0.4375 / 2 = 0.875 of s1².
    common = rng.normal(0, 1, (k, 2))
    other = 2 * (0.75 * common + np.sqrt(1 - 0.75**2) * rng.normal(0, 1, (k, 2)))
    correlated = np.stack([common, other], axis=1)
    ratio = oracle_weighting_mse(correlated, seen, 0) / (common**2).sum(-1).mean()
    assert ratio == pytest.approx(0.875, abs=0.01)
    # Steps where only the best drone predicted count with its own error; other drones' steps
    # and NaNs where a drone did not predict are ignored.
    seen[: k // 2, 1] = False
    errors[: k // 2, 1] = np.nan
    half = (errors[: k // 2, 0] ** 2).sum(-1).sum()
    expected = (half + 0.8 * (errors[k // 2 :, 0] ** 2).sum(-1).sum()) / k
    assert oracle_weighting_mse(errors, seen, 0) == pytest.approx(expected, rel=0.02)
    assert np.isnan(oracle_weighting_mse(errors, np.zeros((k, 2), bool), 0))


def test_replay_with_a_second_filter_for_the_tracks(tmp_path):
    # The recommended setting's Case 2: the tracks are a q = 30 filter's, the labels the
    # fusion's own (q = 1).
    _episode(tmp_path / "ep")
    episode = load_episode(tmp_path / "ep")
    one = replay(episode, _filters(random_walk_planner_psd=None, temporal_kernel=False))
    two = replay(episode, _filters(temporal_kernel=False))
    fast = replay(episode, CloudFusion(two.fusion.planner))

    assert two.fusion.planner.acceleration_psd == 30.0 and one.fusion.planner is None
    assert two.fused_mse == fast.fused_mse != one.fused_mse  # the planner's filter
    assert two.rejections == fast.rejections
    assert two.label_mse == one.label_mse != fast.label_mse  # the fusion's own filter
    assert "a second filter with q = 30.0" in format_result(two)


def test_replay_with_the_temporal_kernel_moves_the_tracks_not_the_labels(tmp_path):
    # The tracks are the kernel's, the labels the filter's.
    _episode(tmp_path / "ep")
    episode = load_episode(tmp_path / "ep")
    plain = replay(episode, _one_filter())
    kernel = replay(episode, _one_filter(temporal_kernel=TEMPORAL_KERNEL))

    assert kernel.fused_mse != plain.fused_mse
    assert kernel.label_mse == plain.label_mse and kernel.rejections == plain.rejections
    assert "a 5-tap temporal kernel" in format_result(kernel)
    assert "temporal kernel" not in format_result(plain)


def test_replay_splits_the_fused_error_by_the_drones_that_saw_the_target(tmp_path):
    # Drone 1 loses target 3 for steps 50-59: its track coasts on the motion model there.
    prediction, _ = _episode(tmp_path / "ep")
    with np.load(tmp_path / "ep" / "episode.npz") as saved:
        arrays = dict(saved)
    arrays["prediction"][50:60, 0, 2] = np.nan
    np.savez(tmp_path / "ep" / "episode.npz", **arrays)
    episode = load_episode(tmp_path / "ep")

    result = replay(episode, _one_filter("paper"))

    views = result.by_views
    # Target 2 is seen by drones 1 and 2 at all 150 steps, targets 1 and 3 by drone 1 alone but
    # for the 10 blanked steps.
    assert [views[v].cells for v in ("2+", "1", "0")] == [150, 290, 10]
    assert sum(v.share for v in views.values()) == pytest.approx(1.0, rel=1e-12)
    cells = sum(v.cells for v in views.values())
    assert sum(v.mse * v.cells for v in views.values()) / cells == pytest.approx(
        result.fused_mse, rel=1e-12
    )
    # Coasting 10 steps at constant velocity drifts further than a measured track.
    assert views["0"].mse > views["1"].mse


def test_replay_command_writes_json_and_markdown(tmp_path):
    _episode(tmp_path / "ep")
    runner = CliRunner()
    out = tmp_path / "out"
    result = runner.invoke(
        app, ["replay", str(tmp_path / "ep"), "--setting", "paper", "--out", str(out)]
    )
    assert result.exit_code == 0, result.output
    assert "| target | drone 1 | drone 2 |" in result.output
    data = json.loads((out / "replay.json").read_text())
    assert data["labels"] == "filtered"
    assert data["fusion"]["fusion"]["method"] == "paper"
    assert len(data["targets"]) == 3
    assert data["targets"][1]["oracle_over_best"] < 1.0
    assert "| oracle / best |" in result.output
    assert (out / "replay.md").read_text().startswith("Replay of")


def test_as_flown_starts_from_the_episodes_setting_and_set_changes_it(tmp_path):
    _, truth = _episode(tmp_path / "ep")
    _records_checkpoint(tmp_path / "ep", truth)  # drone.detected_only reads the detected flags
    runner = CliRunner()
    refused = runner.invoke(app, ["replay", str(tmp_path / "ep"), "--as-flown"])
    assert refused.exit_code == 2 and "metrics.json: records no setting" in refused.output
    flown = Setting.load("paper", ["drone.detected_only=true"])
    _record_setting(tmp_path / "ep", flown)
    episode = load_episode(tmp_path / "ep")
    assert episode.setting == flown and episode.withheld

    out = tmp_path / "out"
    argv = ["replay", str(tmp_path / "ep"), "--as-flown", "--set", "fusion.constant_speed_psd=0.5"]
    result = runner.invoke(app, [*argv, "--out", str(out)])
    assert result.exit_code == 0, result.output
    used = json.loads((out / "replay.json").read_text())
    assert used["fusion"]["fusion"]["method"] == "paper" and used["labels"] == "filtered"
    # Without --as-flown: the named setting (recommended by default).
    runner.invoke(app, ["replay", str(tmp_path / "ep"), "--out", str(out)])
    assert json.loads((out / "replay.json").read_text())["fusion"]["fusion"]["method"] == "robust"


def test_bad_episode_folders_fail_with_one_line(tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["replay", str(tmp_path / "missing")])
    assert result.exit_code == 2
    assert "episode.npz: not found" in result.output
    _episode(tmp_path / "ep")
    (tmp_path / "ep" / "metrics.json").write_text("{}")
    with pytest.raises(EpisodeError, match="metrics.json"):
        load_episode(tmp_path / "ep")
    result = runner.invoke(app, ["replay", str(tmp_path / "ep")])
    assert result.exit_code == 2


def test_bad_settings_are_named(tmp_path):
    _episode(tmp_path / "ep")
    result = CliRunner().invoke(
        app, ["replay", str(tmp_path / "ep"), "--set", "fusion.method=kalman"]
    )
    assert result.exit_code == 2
    assert "fusion.method: 'kalman'" in result.output


def _records_checkpoint(folder, truth, undetected=None):
    """A checkpoint holding only the drones' onboard records: every drone hovers at (15, 5) m
    and detects every target exactly (box centres projected from the truth), but where
    ``undetected(drone index, record)`` hides some."""
    scenario = load_scenario("case2")
    camera = PinholeCamera.from_spec(scenario.camera)
    height = scenario.vehicle.height / 2
    records = []
    for drone in scenario.drones:
        n = len(truth)
        record = OnboardRecord(drone.id, drone.altitude, scenario.target_ids, drone.targets, n, {})
        record.odometry[:, :3] = (15.0, 5.0, drone.altitude)
        points = np.concatenate([truth, np.full((*truth.shape[:2], 1), height)], axis=-1)
        uv, _ = camera.project(points, record.odometry[0, :3], 0.0)
        record.boxes[..., :2], record.boxes[..., 2:] = uv, 0.02
        record.detected[:] = True
        record.steps = n
        if undetected is not None:
            undetected(len(records), record)
        records.append(record.state())
    empty = dict.fromkeys(f.name for f in fields(LoopCheckpoint))
    save_loop_checkpoint(folder / CHECKPOINT_NAME, LoopCheckpoint(**{**empty, "records": records}))


def test_replay_rebuilds_the_drones_noise_reports_from_their_records(tmp_path):
    prediction, truth = _episode(tmp_path / "ep", n_steps=400)
    episode = load_episode(tmp_path / "ep")
    with pytest.raises(EpisodeError, match="resume.npz: not found"):
        drone_reports(episode)
    _records_checkpoint(tmp_path / "ep", truth)
    _, reports = drone_reports(episode)
    # Exact detections: each report is the EMA of the prediction's own squared error:
    # 0.5^2 per axis for drone 1, 0.2^2 for drone 2 on target 2; none for drone 3.
    final = reports[-1]
    assert np.trace(final[0, 1]) == pytest.approx(2 * 0.25, rel=0.35)
    assert np.trace(final[1, 1]) == pytest.approx(2 * 0.04, rel=0.35)
    assert np.isnan(final[2]).all() and np.isnan(final[1, 0]).all()
    result = replay(episode, _one_filter(noise_split="reported"))
    assert result.fusion.fusion.noise_split == "reported"
    assert result.targets[1].fused_over_best < 1.0
    runner = CliRunner()
    ok = runner.invoke(app, ["replay", str(tmp_path / "ep"), "--set", "drone.correct_bias=false"])
    assert ok.exit_code == 0, ok.output


def test_replay_corrects_the_drones_bias_as_they_would_in_flight(tmp_path):
    folder = tmp_path / "ep"
    _, truth = _episode(folder, n_steps=400)
    with np.load(folder / "episode.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays["prediction"][:, 0] += (0.6, -0.4)  # drone 1 off by a constant 0.72 m
    np.savez(folder / "episode.npz", **arrays)
    _records_checkpoint(folder, truth)
    episode = load_episode(folder)
    config = _one_filter()
    raw = replay(episode, config)
    corrected = replay(episode, config, correct_bias=True)
    assert corrected.correct_bias and not raw.correct_bias
    for before, after in zip(raw.targets, corrected.targets, strict=True):
        drone1 = {d.drone_id: d.mse for d in before.drones}[1]
        drone1_after = {d.drone_id: d.mse for d in after.drones}[1]
        assert drone1 == pytest.approx(0.5 + 0.52, rel=0.2)  # noise 2 x 0.25 + offset²
        assert drone1_after < 0.7  # the offset is gone after the EMA's first ~50 steps
    assert "bias-corrected" in CliRunner().invoke(app, ["replay", str(folder)]).output
    # An episode whose drones corrected in flight is not corrected twice, nor uncorrected.
    _record_setting(folder, Setting.load())
    flown = load_episode(folder)
    with pytest.raises(EpisodeError, match="corrected in flight already"):
        replay(flown, config, correct_bias=True)
    assert not replay_setting(flown, Setting.load()).correct_bias
    with pytest.raises(EpisodeError, match="drone.correct_bias = true"):
        replay_setting(flown, Setting.load("paper"))


def test_replay_fuses_only_what_the_drones_detected(tmp_path):
    # Drone 1 loses target 2 from view for steps 100-199 and its predictions there are 1 m
    # off; drone 2 sees it all along. With --detected-only those 100 predictions are not
    # fused (nor counted in drone 1's error): the replay is that of an episode without them.
    folder = tmp_path / "ep"
    _, truth = _episode(folder, n_steps=400)
    with np.load(folder / "episode.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    arrays["prediction"][100:200, 0, 1] += (1.0, 0.0)
    np.savez(folder / "episode.npz", **arrays)

    def hide(i, record):
        if i == 0:
            record.detected[100:200, 1] = False

    _records_checkpoint(folder, truth, hide)
    episode = load_episode(folder)
    config = _one_filter()
    every, detected = replay(episode, config), replay(episode, config, detected_only=True)
    assert detected.detected_only and not every.detected_only
    assert every.measurements - detected.measurements == 100
    drone1 = {d.drone_id: d for d in detected.targets[1].drones}[1]
    assert drone1.n == every.targets[1].drones[0].n - 100
    assert drone1.mse == pytest.approx(every.targets[0].drones[0].mse, rel=0.3)  # no offset
    assert "only those made while the drone detected" in format_result(detected)
    without = {**arrays, "prediction": arrays["prediction"].copy()}
    without["prediction"][100:200, 0, 1] = np.nan
    gone = replay(replace(episode, prediction=without["prediction"], sent=None), config)
    assert detected.fused_mse == gone.fused_mse and detected.label_mse == gone.label_mse
    # An episode flown with --detected-only says what it sent: its replay fuses that alone.
    arrays["sent"] = np.isfinite(arrays["prediction"]).all(axis=-1)
    arrays["sent"][100:200, 0, 1] = False
    np.savez(folder / "episode.npz", **arrays)
    flown = replay(load_episode(folder), config)
    assert (flown.measurements, flown.fused_mse) == (detected.measurements, detected.fused_mse)
    arrays["sent"] = arrays["sent"][:-1]
    np.savez(folder / "episode.npz", **arrays)
    with pytest.raises(EpisodeError, match="sent has shape"):
        load_episode(folder)


def test_the_recorded_setting_reads_back_as_flown(tmp_path):
    # What `track` and `deploy up` write into metrics.json is what `replay --as-flown` reads.
    _episode(tmp_path / "ep")
    setting = Setting.load("recommended", ["fusion.random_walk_planner_psd=10"])
    _record_setting(tmp_path / "ep", setting)
    episode = load_episode(tmp_path / "ep")
    assert episode.setting == setting and episode.bias_corrected and episode.withheld
    (tmp_path / "ep" / "metrics.json").write_text(
        json.dumps({"config": {"scenario": "case2", "setting_values": {"fusion": {}}}})
    )
    with pytest.raises(EpisodeError, match="metrics.json: setting"):
        load_episode(tmp_path / "ep")


def test_a_deployed_episode_replays_with_the_reports_the_cloud_received(tmp_path):
    # `deploy up` writes reports.npz beside episode.npz: the noise each prediction came with.
    # They are fused as received (nothing withheld or rebuilt: the records stay on the drones).
    prediction, _ = _episode(tmp_path / "ep")
    config = _one_filter(noise_split="reported")
    noise = np.full((*prediction.shape[:3], 2, 2), np.nan)
    noise[:, 0] = 0.25 * np.eye(2)  # drones 1 and 2 report their true noise (the split
    noise[:, 1, 1] = 0.04 * np.eye(2)  # acts where two drones see a target: target 2)
    np.savez(tmp_path / "ep" / REPORTS_NAME, noise=noise)
    episode = load_episode(tmp_path / "ep")
    assert episode.received_reports is not None
    # --detected-only (as flown) withholds nothing: what the cloud received was what was sent.
    reported, plain = replay(episode, config, detected_only=True), replay(episode, config)
    assert (reported.fused_mse, reported.label_mse, reported.measurements) == (
        plain.fused_mse,
        plain.label_mse,
        plain.measurements,
    )
    ignored = replay(episode, _one_filter())
    assert reported.fused_mse != ignored.fused_mse
    with pytest.raises(EpisodeError, match="the drones' records stay on the drones"):
        replay(episode, config, correct_bias=True)
    np.savez(tmp_path / "ep" / REPORTS_NAME, noise=noise[:-1])
    with pytest.raises(EpisodeError, match=f"{REPORTS_NAME}: noise has shape"):
        load_episode(tmp_path / "ep")


def test_the_temporal_oracle_averages_white_errors_over_its_taps():
    # Two drones, a parked target, white errors of one variance: the best linear filter of
    # their last K predictions is their plain mean, MSE sigma^2 / (2K) against the best's
    # sigma^2 (taps = 1: the fixed-weights oracle, 1/2).
    rng = np.random.default_rng(3)
    k = 20_000
    truth = np.tile([4.0, -2.0], (k, 1))
    prediction = truth[:, None] + rng.normal(0.0, 0.5, (k, 2, 2))
    for taps in (1, 5):
        oracle = temporal_oracle(prediction, truth, best=0, taps=taps)
        assert oracle.steps == k - taps + 1
        assert oracle.ratio == pytest.approx(1 / (2 * taps), rel=0.05)
        assert oracle.overall == pytest.approx(oracle.ratio, rel=0.01)  # all but taps - 1
    # A moving target and errors that lag it: a static weighting cannot help, the taps can
    # (extrapolating the predictions' own motion).
    t = np.arange(k) * DT
    truth = np.stack([np.sin(0.3 * t) * 20.0, np.cos(0.2 * t) * 10.0], axis=-1)
    late = np.roll(truth, 1, axis=0)  # each prediction one step behind
    late[0] = np.nan
    prediction = np.stack([late, late], axis=1) + rng.normal(0.0, 0.01, (k, 2, 2))
    prediction[:, 1, :][: k // 4] = np.nan  # drone 2 missing for a quarter: only drone 1 there
    fixed = temporal_oracle(prediction, truth, best=0, taps=1)
    temporal = temporal_oracle(prediction, truth, best=0, taps=3)
    assert fixed.ratio > 0.9 and temporal.ratio < 0.05 * fixed.ratio
    assert temporal.steps == k - k // 4 - 2
    # Over all of drone 1's steps the quarter without drone 2 counts with drone 1's own error.
    own = ((late[1:] - truth[1:]) ** 2).sum(-1)
    assert temporal.overall == pytest.approx(own[: k // 4 + 1].sum() / own.sum(), rel=0.05)
    # Too few steps: no figure.
    short = temporal_oracle(prediction[:30], truth[:30], best=0)
    assert short.steps == 0 and np.isnan(short.ratio) and np.isnan(short.overall)
