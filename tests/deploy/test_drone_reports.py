"""The deployed drone's noise reports, bias correction and withheld predictions (the setting's
``[drone]``), without processes: its uplink is a
prediction message followed by a noise report; the reports and the corrected predictions are
those the replay rebuilds from the drone's own record (the closed loop's computation); a new
model gets its own bias; only the targets it detects are sent."""

import copy

import numpy as np
import pytest

from dronefl.config import load_scenario
from dronefl.deploy.drone import DroneProcess, DroneSettings
from dronefl.deploy.messages import SenseMessage
from dronefl.experiments.pretrain import PretrainSpec
from dronefl.models.model import build_model
from dronefl.models.predictor import TrajectoryPredictor
from dronefl.perception import make_detector
from dronefl.settings import Setting
from dronefl.sim.camera import PinholeCamera
from dronefl.sim.world import World
from dronefl.tracking.reports import box_ground_positions, forecast_residual_reports
from dronefl.wire import NoiseReportMessage, PredictionMessage, split_uplink

STEPS = 60


def _setting(noise_reports=False, correct_bias=False, detected_only=False) -> Setting:
    drone = {"noise_reports": noise_reports, "correct_bias": correct_bias}
    return Setting.load().with_values(drone={**drone, "detected_only": detected_only})


def _fly(tmp_path, **options):
    """One case 2 drone (id 2: two targets, each shared with another drone) fed STEPS of the
    world's senses, sending what ``options`` (:func:`_setting`) say; returns the drone, its
    sent predictions ``(STEPS, 1, N, 2)`` and its noise reports by step."""
    scenario = load_scenario("case2")
    drone_id = 2
    setting = _setting(**options)
    predictor = TrajectoryPredictor(
        build_model(PretrainSpec(scenario, setting).model, seed=0), runtime="torch"
    )
    settings = DroneSettings(
        "case2", drone_id, tmp_path / "model.npz", tmp_path, setting, ("127.0.0.1:1",),
        "127.0.0.1:2", 3,
    )  # fmt: skip
    info = {"dt": scenario.dt, "scenario": "case2", "environment": "orchard", "seed": 0,
            "steps": STEPS}  # fmt: skip
    drone = DroneProcess(settings, info, predictor)
    world = World(scenario, "orchard", 0)
    detector = make_detector("projection", world)
    index = scenario.drone_ids.index(drone_id)
    predictions = np.full((STEPS, 1, len(scenario.target_ids), 2), np.nan)
    reports = []
    for k in range(STEPS):
        odometry, view = world.odometry()[index], world.camera_views()[index]
        sense = SenseMessage(k, odometry, tuple(detector.detect(view)))
        uplink, report = split_uplink(drone.predict(sense.encode()))
        message = PredictionMessage.decode(uplink)
        for target_id, position in zip(message.target_ids, message.positions[:, 0], strict=True):
            predictions[k, 0, scenario.target_ids.index(target_id)] = position
        past_steps = setting.model.past_steps
        if k < past_steps - 1 or not setting.drone.noise_reports:  # no window or no reports
            assert report == b""
            assert k >= past_steps - 1 or message.target_ids == ()
        else:
            reports.append((k, NoiseReportMessage.decode(report)))
        world.step(np.zeros((len(scenario.drones), 2)))
    return drone, predictions, reports


def _ground(drone):
    """The drone's detections back-projected as its reporter does."""
    scenario = load_scenario("case2")
    record = drone.record
    boxes = np.where(record.detected[:, :, None], record.boxes, np.nan)
    camera = PinholeCamera.from_spec(scenario.camera)
    return box_ground_positions(camera, boxes, record.odometry, scenario.vehicle.height / 2)


@pytest.fixture(scope="module")
def flown(tmp_path_factory):
    """The same drone flown plain and with noise reports and the bias correction."""
    root = tmp_path_factory.mktemp("drones")
    raw = _fly(root / "raw")
    return raw, _fly(root / "corrected", noise_reports=True, correct_bias=True)


def test_a_reporting_drone_sends_the_reports_its_record_gives(flown):
    _, (drone, sent, reports) = flown
    target_ids = load_scenario("case2").target_ids
    _, expected = forecast_residual_reports(sent, [_ground(drone)])  # of what it sent
    compared = 0
    for k, report in reports:
        assert report.drone_id == 2 and report.step == k
        for target_id, noise in zip(report.target_ids, report.noise, strict=True):
            want = expected[k, 0, target_ids.index(target_id)]
            np.testing.assert_allclose(noise, want, rtol=2e-3, atol=1e-4)  # half floats
            compared += 1
    assert compared > 50


def test_a_correcting_drone_sends_what_the_replay_rebuilds(flown):
    # The same drone without and with the correction: the corrected predictions are the raw
    # ones less the running mean of the residuals of what was sent.
    (_, raw, no_reports), (drone, sent, _) = flown
    assert no_reports == []
    expected, _ = forecast_residual_reports(raw, [_ground(drone)], correct_bias=True)
    np.testing.assert_allclose(sent, expected, atol=0.011)  # centimetres on the radio
    assert np.nanmax(np.abs(sent - raw)) > 0.05  # and it did correct


def test_a_drone_that_corrects_without_reporting_sends_the_same_predictions(flown, tmp_path):
    _, (_, reporting, _) = flown
    _, sent, reports = _fly(tmp_path, correct_bias=True)
    assert reports == []  # predictions only on the radio
    np.testing.assert_array_equal(sent, reporting)


def test_a_new_model_gets_its_own_bias_from_the_drones_record(flown):
    # Re-estimated with the model flown, the bias is the one the drone kept in flight (the
    # same residuals, but for the centimetres on the radio); with another model it is that
    # model's: the EMA of its own residuals over the record.
    _, (drone, _, _) = flown
    reporter, record = copy.deepcopy(drone.node.reporter), drone.record
    past_steps = drone.node.past_steps
    kept = reporter.residual.bias()
    reporter.rebase(record, drone.predictor, past_steps)
    np.testing.assert_allclose(reporter.residual.bias(), kept, atol=0.01)
    other = TrajectoryPredictor(
        build_model(PretrainSpec(load_scenario("case2"), Setting.load()).model, seed=1),
        runtime="torch",
    )
    raw = np.full((STEPS, 1, len(record.target_ids), 2), np.nan)
    for k in range(past_steps - 1, STEPS):
        window = slice(k + 1 - past_steps, k + 1)
        raw[k, 0, record.assigned] = other.predict(
            record.odometry[window], record.boxes[window][:, record.assigned],
            record.detected[window][:, record.assigned],
        )[:, 0]  # fmt: skip
    reporter.rebase(record, other, past_steps)
    ema = np.zeros((len(record.target_ids), 2))
    ground = _ground(drone)
    for k in range(STEPS - 1):
        e = raw[k, 0] - ground[k + 1]
        ok = np.isfinite(e).all(axis=1)
        ema[ok] += reporter.residual.rate * (e[ok] - ema[ok])
    np.testing.assert_allclose(reporter.residual.bias(), ema, atol=1e-9)
    assert np.abs(ema - kept).max() > 0.05


def test_split_uplink_without_a_report_and_with_a_short_payload():
    message = PredictionMessage(1, 3, (2,), np.ones((1, 1, 2))).encode()
    assert split_uplink(message) == (message, b"")
    assert split_uplink(b"\x02") == (b"\x02", b"")


def test_a_drone_that_sends_only_what_it_detects(flown, tmp_path):
    # drone.detected_only: the predictions of the targets it detects at that step, corrected
    # by the residuals of what it sent (the replay's computation), no others.
    (_, raw, _), _ = flown
    drone, sent, reports = _fly(tmp_path, noise_reports=True, correct_bias=True, detected_only=True)
    detected = drone.record.detected[:STEPS]  # (STEPS, N)
    made = np.isfinite(raw[:, 0]).all(axis=-1)
    assert np.array_equal(np.isfinite(sent[:, 0]).all(axis=-1), made & detected)
    assert (made & ~detected).sum() > 0 and (made & detected).sum() > 50
    withheld = np.where(detected[:, None, :, None], raw, np.nan)
    expected, _ = forecast_residual_reports(withheld, [_ground(drone)], correct_bias=True)
    np.testing.assert_allclose(sent, expected, atol=0.011)  # centimetres on the radio
    assert all(set(r.target_ids) <= set(np.nonzero(detected[k])[0] + 1) for k, r in reports)
    # Its reports are those the replay rebuilds from what it sent.
    _, rebuilt = forecast_residual_reports(sent, [_ground(drone)])
    target_ids = load_scenario("case2").target_ids
    for k, report in reports:
        for target_id, noise in zip(report.target_ids, report.noise, strict=True):
            want = rebuilt[k, 0, target_ids.index(target_id)]
            np.testing.assert_allclose(noise, want, rtol=2e-3, atol=1e-4)  # half floats
