"""The closed loop: metrics by hand, the onboard record, pseudo-labels, a short episode."""

import json
import pickle
from dataclasses import replace

import numpy as np
import pytest
import torch
from PIL import Image

from dronefl.cli import _as_flags
from dronefl.config import load_scenario
from dronefl.experiments.episode import EpisodeLog, EpisodeMetrics, tracking_metrics
from dronefl.experiments.loop_checkpoint import CHECKPOINT_NAME
from dronefl.experiments.pretrain import PretrainSpec
from dronefl.experiments.track import RECOMMENDED, TrackConfig, run_episode
from dronefl.fl.checkpoint import load_checkpoint
from dronefl.learners import LearnerSetup
from dronefl.learners.centralized import CentralizedLearner
from dronefl.learners.federated import session_settings
from dronefl.logs import LogError, PseudoLabels
from dronefl.models.model import build_model
from dronefl.models.online import OnboardRecord
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
    log.sent[0, 0, 0] = False  # withheld (--detected-only): still made, not sent
    withheld = tracking_metrics(log, scenario)
    assert withheld.prediction_error == pytest.approx(5.0)
    assert withheld.sent_prediction_error == pytest.approx(9.0)


def test_metrics_written_before_the_sent_predictions_error_load_it_as_unknown():
    from dronefl.experiments.episode import TrackingMetrics
    from dronefl.results import from_json

    old = {"prediction_error": 1.0, "tracking_distance": 2.0, "uncertainty": 0.1,
           "speed_change": 0.2, "total_cost": 3.0, "prediction_coverage": 0.9,
           "tracking_error": 0.5}  # fmt: skip
    assert np.isnan(from_json(TrackingMetrics, old).sent_prediction_error)


def test_a_log_says_which_predictions_were_sent_also_one_pickled_before():
    log = EpisodeLog.empty(load_scenario("case1"), 3)
    log.prediction[0, 0, 0] = log.prediction[1, 1, 1] = (1.0, 2.0)
    log.sent[1, 1, 1] = True  # the first was made but withheld (--detected-only)
    received = log.sent_predictions()
    assert np.isnan(received[0, 0, 0]).all() and received[1, 1, 1].tolist() == [1.0, 2.0]
    assert tracking_metrics(log, load_scenario("case1")).prediction_coverage == 2 / 6
    # A log pickled before `sent` existed sent every prediction it holds.
    old = pickle.loads(pickle.dumps(log))
    del old.__dict__["sent"]
    loaded = pickle.loads(pickle.dumps(old))
    assert loaded.sent[0, 0, 0] and loaded.sent[1, 1, 1] and loaded.sent.sum() == 2


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


@pytest.mark.slow
def test_a_drone_with_no_lower_view_keeps_its_model(quick_pretrained_case2, tmp_path):
    pretrained = quick_pretrained_case2
    case2 = PretrainSpec(load_scenario("case2"), "dronefl").settings(pretrained)
    state = load_checkpoint(case2.checkpoint_path, case2.history_path, "dronefl").state
    config = TrackConfig(
        scenario=load_scenario("case2"), method="dronefl", seed=3, duration=24.0,
        environment="crop_field", fl_period=20.0, epochs=1, label_drones="lower",
        runtime="torch", pretrained=pretrained, out=tmp_path / "episode", progress=False,
        animate=False,
    )  # fmt: skip
    metrics = run_episode(config)

    # Drone 3 flies lowest (25 m): no label of its holds a lower view, so it sits out the
    # round and keeps flying the pretrained model; drone 1 (45 m) learns from drones 2-3.
    (only,) = metrics.fl_rounds
    assert 1 in only.train_loss and 3 not in only.train_loss
    assert "drone 3: no training examples" in only.rejected
    with (tmp_path / "episode" / CHECKPOINT_NAME).open("rb") as handle:
        predictors = pickle.load(handle).predictors
    for key, value in state.items():
        assert torch.equal(predictors[3][key], value), key
    assert not torch.equal(predictors[1]["embed.weight"], state["embed.weight"])


def test_the_preset_sets_the_episode_models_and_their_updates(tmp_path):
    case1 = load_scenario("case1")
    ours, sgd = TrackConfig(case1, tmp_path), TrackConfig(case1, tmp_path, preset="metric-sgd")

    # Unset E and lr are the preset's; given ones win.
    assert (ours.epochs, ours.lr, sgd.epochs, sgd.lr) == (10, 1e-3, 10, 3e-4)
    assert TrackConfig(case1, tmp_path, preset="metric-sgd", lr=1e-4).lr == 1e-4
    assert sgd.settings()["preset"] == "metric-sgd"  # another preset is another episode
    assert sgd.pretrain_spec().model.box_size == "metric"
    assert ours.pretrain_spec() == PretrainSpec(case1, "dronefl", stride=2)
    with pytest.raises(ValueError, match="--config: 'nope'"):
        TrackConfig(case1, tmp_path, preset="nope")

    # The online rounds train the preset's model with its batch and optimiser.
    setup = LearnerSetup(tmp_path, {}, 10, 2, 3, 0, 1e-4, preset="metric-sgd")
    rounds = session_settings(setup)
    assert (rounds.epochs, rounds.lr, rounds.batch_size, rounds.optimizer) == (3, 1e-4, 64, "sgd")
    assert (rounds.model, rounds.labels, rounds.train_fraction) == (
        sgd.pretrain_spec().model,
        "tracks",
        1.0,
    )
    large = PretrainSpec(case1, "centralized", preset="metric-sgd").model
    learner = CentralizedLearner(replace(setup, state=build_model(large).state_dict()))
    assert learner.settings.model == large and learner.settings.optimizer == "sgd"


def test_the_demo_flies_the_recommended_setting_and_track_keeps_the_papers(
    tmp_path, quick_pretrained_case2
):
    case2 = load_scenario("case2")
    recommended = TrackConfig(case2, tmp_path, pretrained=quick_pretrained_case2, **RECOMMENDED)
    assert (
        recommended.preset,
        recommended.label_drones,
        recommended.epochs,
        recommended.noise_split,
        recommended.correct_bias,
        recommended.detected_only,
        recommended.planner_distance,
        recommended.constant_speed_psd,
    ) == ("metric-scaffold", "others", 1, "reported", True, True, "rest", 1e-3)
    assert recommended.lr == 3e-4  # the preset's, as the README's Table I was flown
    assert _as_flags(RECOMMENDED) == (  # what `dronefl demo` prints under its table
        "--config metric-scaffold --label-drones others --epochs 1 --noise-split reported "
        "--correct-bias --detected-only --planner-distance rest --constant-speed-psd 0.001 "
        "--random-walk-track-psd 30.0 --temporal-kernel --pretrain-gaps auto"
    )
    assert recommended.planner_track_psd == 30.0  # Case 2's random walk: a second filter
    assert recommended.track_fusion_config().temporal_kernel is not None
    spec = recommended.pretrain_spec()  # the quick models' stand-in choice: no gaps
    assert (spec.preset, recommended.pretrain_gaps, spec.detection_gaps) == (
        "metric-scaffold",
        "auto",
        0.0,
    )
    default = TrackConfig(case2, tmp_path)  # the paper's online setting
    assert (default.preset, default.label_drones, default.epochs) == ("ours", "all", 10)
    assert default.noise_split == "adaptive" and not default.correct_bias
    assert not default.detected_only and default.planner_distance == "next"
    assert default.constant_speed_psd is None and default.fusion_config().acceleration_psd == 1.0


def test_the_constant_speed_q_reaches_the_fusion_and_names_episodes_through_it(tmp_path):
    case3 = TrackConfig(load_scenario("case3"), tmp_path, constant_speed_psd=1e-3)
    assert case3.fusion_config().acceleration_psd == case3.track_fusion_config().acceleration_psd
    assert case3.fusion_config().acceleration_psd == 1e-3
    paper = replace(case3, constant_speed_psd=None)
    assert paper.fusion_config().acceleration_psd == 0.1
    assert "constant_speed_psd" not in case3.describe()  # its q is in fusion_config
    assert case3.settings() != paper.settings()
    case2 = replace(case3, scenario=load_scenario("case2"))  # random walk: the same episode
    assert case2.settings() == replace(case2, constant_speed_psd=None).settings()
    with pytest.raises(ValueError, match="--constant-speed-psd"):
        replace(case3, constant_speed_psd=0.0)


def test_the_planner_distance_is_a_setting_old_episodes_keep_without_it(tmp_path):
    config = TrackConfig(load_scenario("case1"), tmp_path, planner_distance="rest")
    assert config.planner_config().distance_at == "rest"
    assert config.describe()["planner_distance"] == "rest"
    paper = replace(config, planner_distance="next")
    assert paper.planner_config().distance_at == "next"
    assert "planner_distance" not in paper.describe()  # as every episode flown before it
    with pytest.raises(ValueError, match="--planner-distance"):
        replace(config, planner_distance="later")


@pytest.mark.slow
def test_a_second_filter_at_the_fusions_own_q_flies_the_one_filter_episode(
    quick_pretrained_case2, tmp_path
):
    # Case 2's recommended setting flies the planner on a q = 10 filter; `--track-psd 1` (the
    # fusion's own q) gives back the one-filter episode to the bit, the way to reproduce a
    # recommended Case 2 figure flown before the second filter joined the setting.
    one = TrackConfig(
        scenario=load_scenario("case2"), method="fixed", seed=3, duration=12.0,
        environment="crop_field", runtime="torch", pretrained=quick_pretrained_case2,
        out=tmp_path / "one", progress=False, animate=False,
    )  # fmt: skip
    assert one.planner_track_psd is None and one.fusion_config().acceleration_psd == 1.0
    logs = {}
    for name, config in (
        ("one", one),
        ("own q", replace(one, track_psd=1.0, out=tmp_path / "own")),
        ("q 10", replace(one, random_walk_track_psd=10.0, out=tmp_path / "fast")),
    ):
        run_episode(config)
        with np.load(config.out / "episode.npz") as episode:
            logs[name] = {key: episode[key] for key in episode.files}
    for key, value in logs["one"].items():
        np.testing.assert_array_equal(logs["own q"][key], value, err_msg=key)
    assert not np.array_equal(logs["q 10"]["track_position"], logs["one"]["track_position"])


@pytest.mark.slow
def test_a_second_filter_flies_the_tracks_and_the_labels_keep_their_own(quick_pretrained, tmp_path):
    config = TrackConfig(
        scenario=load_scenario("case1"), method="fixed", seed=3, duration=12.0,
        environment="crop_field", runtime="torch", pretrained=quick_pretrained, out=tmp_path,
        progress=False, animate=False, track_psd=10.0,
    )  # fmt: skip
    run_episode(config)

    with (tmp_path / CHECKPOINT_NAME).open("rb") as handle:
        saved = pickle.load(handle)
    tracks, labels = saved.fuser, saved.label_fuser
    # The planner's filter has q = 10; the labels' is the fusion's own, fed the same stream.
    assert tracks.config == replace(config.fusion_config(), acceleration_psd=10.0)
    assert labels.config == config.fusion_config() and labels.config.acceleration_psd != 10.0
    assert labels.measurements == tracks.measurements > 0
    with np.load(tmp_path / "episode.npz") as episode:
        logged, trace = episode["track_position"], episode["trace"]
    for j, target in enumerate(config.scenario.target_ids):
        mine, theirs = tracks.history(target), labels.history(target)
        np.testing.assert_array_equal(mine.t, theirs.t)
        # The episode logs the planner's tracks: the last one is the q = 10 filter's.
        np.testing.assert_allclose(logged[-1, j], mine.mean[-1, :2], rtol=0, atol=1e-12)
        # ... and the Tr P of the fusion's own filter, which the planner weighs.
        own = np.trace(theirs.covariance[-1])
        assert trace[-1, j] == pytest.approx(own, rel=1e-12)
        assert abs(np.trace(mine.covariance[-1]) - own) > 1e-6
        assert np.abs(mine.mean[:, :2] - theirs.mean[:, :2]).max() > 1e-3
    assert config.describe()["track_psd"] == 10.0
    assert "track_psd" not in replace(config, track_psd=None).describe()  # old episodes reuse
    with pytest.raises(ValueError, match="--track-psd"):
        replace(config, track_psd=0.0)
