"""The closed loop: metrics by hand, the onboard record, pseudo-labels, a short episode."""

import json
from dataclasses import replace

import numpy as np
import pytest
from PIL import Image
from quick_models import plant_quick_models

from dronefl.config import load_scenario, parse_scenario
from dronefl.experiments.loop_checkpoint import CHECKPOINT_NAME, read_loop_checkpoint
from dronefl.experiments.prepare import prepare
from dronefl.experiments.pretrain import PretrainSpec
from dronefl.experiments.simulate import scenario_dict
from dronefl.experiments.track import TrackConfig, run_episode
from dronefl.learners import LearnerSetup
from dronefl.learners.centralized import CentralizedLearner
from dronefl.learners.federated import session_settings
from dronefl.logs import LogError, PseudoLabels
from dronefl.models.model import build_model
from dronefl.models.online import OnboardRecord
from dronefl.results.episode import EpisodeLog, EpisodeMetrics, tracking_metrics
from dronefl.settings import Setting
from dronefl.tracking import Fuser, cloud_fusion
from dronefl.types import Detection, Odometry


def test_episode_metrics_by_hand():
    scenario = load_scenario("case1")  # drone 1 watches target 1, drone 2 target 2
    k = 2
    log = EpisodeLog(
        t=np.array([0.0, 0.2, 0.4]),
        target_position=np.array([[[0, 0], [10, 0]], [[1, 0], [11, 0]], [[2, 0], [12, 0]]], float),
        drone_position=np.array([[[0, 3], [10, 4]]] * 3, float),
        drone_velocity=np.array([[[0, 0], [0, 0]], [[1, 0], [0, 0]], [[1, 0], [0, 2]]], float),
        prediction=np.full((k, 2, 2, 2), np.nan),
        track_position=np.full((3, 2, 2), np.nan),
        trace=np.array([[1.0, 3.0], [np.nan, 2.0]]),
        cost=np.array([10.0, 20.0]),
    )
    log.prediction[0, 0, 0] = [1, 1]  # truth at k+1 = (1, 0): squared error 1
    log.prediction[1, 1, 1] = [12, 3]  # truth (12, 0): squared error 9
    log.prediction[1, 0, 1] = [0, 0]  # drone 1 does not watch target 2: ignored
    metrics = tracking_metrics(log, scenario)
    assert metrics.prediction_error == pytest.approx(5.0)
    assert metrics.prediction_coverage == pytest.approx(2 / 4)
    # Squared distances at steps 0 and 1: drone 1: 9, 10; drone 2: 16, 17.
    assert metrics.tracking_distance == pytest.approx((9 + 10 + 16 + 17) / 4)
    assert metrics.uncertainty == pytest.approx(2.0)
    # |v1 - v0| per drone over steps 0 -> 1: drone 1 moved 0 -> 1 m/s, drone 2 stayed.
    assert metrics.speed_change == pytest.approx(0.5)
    assert metrics.total_cost == pytest.approx(15.0)
    assert np.isnan(metrics.tracking_error)  # no fused track yet
    assert np.isnan(metrics.sent_prediction_error)  # none was marked sent
    log.sent[0, 0, 0] = log.sent[1, 1, 1] = log.sent[1, 0, 1] = True
    assert tracking_metrics(log, scenario).sent_prediction_error == pytest.approx(5.0)
    log.sent[0, 0, 0] = False  # withheld (drone.detected_only): still made, not sent
    withheld = tracking_metrics(log, scenario)
    assert withheld.prediction_error == pytest.approx(5.0)
    assert withheld.sent_prediction_error == pytest.approx(9.0)


def test_a_log_says_which_predictions_were_sent():
    log = EpisodeLog.empty(load_scenario("case1"), 3)
    log.prediction[0, 0, 0] = log.prediction[1, 1, 1] = (1.0, 2.0)
    log.sent[1, 1, 1] = True  # the first was made but withheld (drone.detected_only)
    received = log.sent_predictions()
    assert np.isnan(received[0, 0, 0]).all() and received[1, 1, 1].tolist() == [1.0, 2.0]
    assert tracking_metrics(log, load_scenario("case1")).prediction_coverage == 2 / 6


def test_onboard_record_windows_and_log():
    record = OnboardRecord(2, 35.0, (1, 2, 3), (1, 2), capacity=4, meta={})
    for k in range(3):
        detections = [Detection(2, (0.5, 0.5, 0.1, 0.1), 0.9)] if k != 1 else []
        record.append(Odometry(0.2 * k, np.full(12, float(k))), detections)
    assert record.window(4) is None
    odometry, boxes, detected = record.window(2)
    assert odometry[:, 0].tolist() == [1.0, 2.0]
    assert boxes.shape == (2, 2, 4) and detected.tolist() == [[False, False], [False, True]]
    log = record.to_log()
    assert log.t.tolist() == pytest.approx([0.0, 0.2, 0.4]) and log.assigned_ids == (1, 2)
    record.append(Odometry(0.6, np.zeros(12)), [])
    with pytest.raises(IndexError, match="onboard record is full"):
        record.append(Odometry(0.8, np.zeros(12)), [])


def test_pseudo_labels_round_trip_and_alignment(tmp_path):
    record = OnboardRecord(1, 30.0, (1, 2), (1,), capacity=2, meta={})
    record.append(Odometry(0.0, np.zeros(12)), [])
    record.append(Odometry(0.2, np.zeros(12)), [])
    labels = PseudoLabels(np.array([0.0, 0.2]), np.array([2, 1]), np.arange(8.0).reshape(2, 2, 2))
    labels.save(tmp_path / "tracks.npz")
    back = PseudoLabels.load(tmp_path / "tracks.npz")
    aligned = back.for_log(record.to_log())  # the log's columns are (1, 2)
    assert aligned[:, 0].tolist() == [[2.0, 3.0], [6.0, 7.0]]
    shifted = PseudoLabels(np.array([0.0, 0.4]), labels.target_ids, labels.position)
    with pytest.raises(LogError, match="another time grid"):
        shifted.for_log(record.to_log())


@pytest.mark.slow
def test_short_closed_loop_episode_keeps_every_target_tracked(quick_pretrained, tmp_path):
    config = TrackConfig(
        scenario=load_scenario("case1"),
        method="fixed",
        seed=3,
        duration=40.0,
        environment="crop_field",
        runtime="torch",
        pretrained=quick_pretrained,
        out=tmp_path,
        progress=False,
    )
    metrics = run_episode(config)
    # Every prediction the drones made and every fused track stay within a few metres.
    tracking = metrics.tracking
    assert tracking.prediction_coverage > 0.9
    assert tracking.prediction_error < 4.0
    assert tracking.tracking_error < 4.0
    # Each drone stays over its target: well inside a 9 m half-footprint (drone 2 at 20 m).
    assert tracking.tracking_distance < 30.0
    assert metrics.fl_rounds == ()
    assert EpisodeMetrics.load(tmp_path / "metrics.json") == metrics
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["tracking"]["prediction_error"] == metrics.tracking.prediction_error
    assert saved["scenario"] == "case1" and saved["method"] == "fixed"
    # The saved episode: 40 s / 0.2 s = 200 steps, 2 targets, 2 drones; from it the tracking
    # distance recomputed by hand (drone 1 over target 1, drone 2 over target 2, steps 0-199).
    with np.load(tmp_path / "episode.npz") as episode:
        assert episode["target_position"].shape == (201, 2, 2)
        assert episode["drone_position"].shape == (201, 2, 2)
        assert episode["prediction"].shape == (200, 2, 2, 2)
        gap = episode["drone_position"][:-1] - episode["target_position"][:-1]  # (200, 2, 2)
    assert metrics.tracking.tracking_distance == pytest.approx(
        (gap**2).sum(axis=-1).mean(), rel=1e-12
    )
    for name in ("trajectories.png", "timeseries.png"):
        with Image.open(tmp_path / name) as image:
            image.load()  # the whole image decodes
            assert image.format == "PNG" and min(image.size) > 300
    # The animation: 100 frames at 10 frames/s, and the vehicles move between the first and
    # the last.
    with Image.open(tmp_path / "episode.gif") as gif:
        assert gif.format == "GIF" and gif.n_frames == 100 and gif.info["duration"] == 100
        first = np.asarray(gif.convert("RGB"))
        gif.seek(gif.n_frames - 1)
        last = np.asarray(gif.convert("RGB"))
    assert first.shape == last.shape and (first != last).any(axis=-1).sum() > 50
    again = run_episode(replace(config, animate=False))  # the GIF is not part of the result
    assert again.tracking == metrics.tracking


def _lonely_case2():
    """Case 2 with drone 3 the only one to watch target 3: with ``others`` it has no label."""
    raw = scenario_dict(load_scenario("case2"))
    raw["name"] = "case2-lonely"
    raw["drones"][0]["targets"] = [1, 2]
    raw["drones"][2]["targets"] = [3]
    return parse_scenario(raw, source="test")


@pytest.mark.slow
def test_a_drone_without_a_label_keeps_its_model(quick_pretrained, tmp_path):
    scenario = _lonely_case2()
    pretrained = plant_quick_models(quick_pretrained, scenario, tmp_path / "pretrained")
    setting = Setting.load("recommended", ["learning.period=20"])
    config = TrackConfig(
        scenario=scenario, setting=setting, method="dronefl", seed=3, duration=24.0,
        environment="crop_field", runtime="torch", pretrained=pretrained,
        out=tmp_path / "episode", progress=False, animate=False,
    )  # fmt: skip
    state = prepare(scenario, setting, "dronefl", pretrained, progress=False).state
    metrics = run_episode(config)

    # Drone 3 alone watches target 3: no other drone's view, no label; it sits out the round
    # and keeps flying the pretrained model, while drones 1 and 2 learn from each other.
    (only,) = metrics.fl_rounds
    assert 1 in only.train_loss and 3 not in only.train_loss
    assert "drone 3: no training examples" in only.rejected
    predictors = read_loop_checkpoint(tmp_path / "episode" / CHECKPOINT_NAME).predictors
    for key, value in state.items():
        assert np.array_equal(predictors[3][key], value.numpy()), key
    assert not np.array_equal(predictors[1]["embed.weight"], state["embed.weight"].numpy())


def test_the_setting_sets_the_episode_models_and_their_updates(tmp_path):
    case1 = load_scenario("case1")
    ours = TrackConfig(case1, tmp_path)
    paper = TrackConfig(case1, tmp_path, setting=Setting.load("paper"))
    assert ours.setting == Setting.load("recommended")  # the Python default is the CLI's
    assert ours.identity()["setting"] != paper.identity()["setting"]  # another episode
    assert PretrainSpec(case1, ours.setting).model.box_size == "metric"
    assert PretrainSpec(case1, paper.setting).model.box_size == "image"
    with pytest.raises(ValueError, match="--method: 'nope'"):
        TrackConfig(case1, tmp_path, method="nope")

    # The online rounds train the setting's model with its batch and optimiser, E the
    # learning's.
    setup = LearnerSetup(tmp_path, {}, ours.setting, 0, (160.0, 120.0))
    rounds = session_settings(setup)
    assert (rounds.epochs, rounds.lr, rounds.batch_size, rounds.optimizer) == (1, 3e-4, 64, "sgd")
    assert (rounds.model, rounds.labels, rounds.train_fraction) == (
        PretrainSpec(case1, ours.setting).model,
        "tracks",
        1.0,
    )
    large = PretrainSpec(case1, ours.setting, "centralized").model
    learner = CentralizedLearner(replace(setup, state=build_model(large).state_dict()))
    assert learner.settings.model == large and learner.settings.optimizer == "sgd"


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("duration", float("inf"), "--duration: must be between 0.2 s and 86400 s"),
        ("duration", float("nan"), "--duration: must be between 0.2 s and 86400 s"),
        ("duration", 0.001, "--duration: must be between 0.2 s and 86400 s"),
        ("duration", 1e6, "--duration: must be between 0.2 s and 86400 s"),
        ("seed", -2, "--seed: must be in"),
        ("environment", "desert", "--env: 'desert' is not one of"),
        ("detector", "radar", "--detector: 'radar' is not one of"),
        ("method", "centralized-image", "needs --detector yolo|use --detector yolo"),
    ],
)
def test_a_bad_episode_is_refused_naming_the_option(tmp_path, field, value, message):
    with pytest.raises(ValueError, match=message):
        TrackConfig(load_scenario("case1"), tmp_path, **{field: value})


@pytest.mark.slow
def test_one_filter_flies_without_a_planner_s_own(quick_pretrained_case2, tmp_path):
    # Case 2's recommended setting flies the planner on a q = 30 filter; without it the
    # planner flies on the fusion's own filter, and the tracks differ.
    logs = {}
    for name, overrides in (("q 30", []), ("one", ["fusion.random_walk_planner_psd=none"])):
        config = TrackConfig(
            scenario=load_scenario("case2"), setting=Setting.load("recommended", overrides),
            method="fixed", seed=3, duration=12.0, environment="crop_field", runtime="torch",
            pretrained=quick_pretrained_case2, out=tmp_path / name, progress=False,
            animate=False,
        )  # fmt: skip
        run_episode(config)
        with np.load(config.out / "episode.npz") as episode:
            logs[name] = {key: episode[key] for key in episode.files}
        saved = read_loop_checkpoint(config.out / CHECKPOINT_NAME)
        assert (saved.label_fuser is None) == (name == "one")
    assert not np.array_equal(logs["q 30"]["track_position"], logs["one"]["track_position"])
    np.testing.assert_array_equal(
        logs["q 30"]["target_position"][:2], logs["one"]["target_position"][:2]
    )


@pytest.mark.slow
def test_a_second_filter_flies_the_tracks_and_the_labels_keep_their_own(
    quick_pretrained_case2, tmp_path
):
    config = TrackConfig(
        scenario=load_scenario("case2"), method="fixed", seed=3, duration=12.0,
        environment="crop_field", runtime="torch", pretrained=quick_pretrained_case2,
        out=tmp_path, progress=False, animate=False,
    )  # fmt: skip
    run_episode(config)

    saved = read_loop_checkpoint(tmp_path / CHECKPOINT_NAME)
    filters = cloud_fusion(config.setting.fusion, True, config.scenario)
    scenario = config.scenario
    tracks = Fuser(scenario.target_ids, scenario.drone_ids, filters.tracks)
    labels = Fuser(scenario.target_ids, scenario.drone_ids, filters.fusion)
    tracks.restore(saved.fuser)
    labels.restore(saved.label_fuser)
    # The planner's filter has q = 30; the labels' is the fusion's own, fed the same stream.
    assert tracks.config.acceleration_psd == 30.0
    assert labels.config.acceleration_psd == 1.0 and labels.config.motion == "mean_reverting"
    assert labels.measurements == tracks.measurements > 0
    with np.load(tmp_path / "episode.npz") as episode:
        trace = episode["trace"]
    for j, target in enumerate(config.scenario.target_ids):
        mine, theirs = tracks.history(target), labels.history(target)
        np.testing.assert_array_equal(mine.t, theirs.t)
        # The episode logs the Tr P of the fusion's own filter, which the planner weighs.
        own = np.trace(theirs.covariance[-1])
        assert trace[-1, j] == pytest.approx(own, rel=1e-12)
        assert abs(np.trace(mine.covariance[-1]) - own) > 1e-6
        assert np.abs(mine.mean[:, :2] - theirs.mean[:, :2]).max() > 1e-3
