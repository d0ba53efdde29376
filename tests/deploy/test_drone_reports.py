"""The deployed drone's noise reports (``dronefl drone --report-noise``), without processes:
its uplink is a prediction message followed by a noise report, and the reports are those the
replay rebuilds from the drone's own record (the closed loop's computation)."""

import numpy as np
import pytest

from dronefl.config import load_scenario
from dronefl.deploy.drone import DroneProcess, DroneSettings
from dronefl.deploy.messages import SenseMessage
from dronefl.experiments.pretrain import PretrainSpec
from dronefl.models.model import build_model
from dronefl.models.predictor import TrajectoryPredictor
from dronefl.perception import make_detector
from dronefl.sim.camera import PinholeCamera
from dronefl.sim.world import World
from dronefl.tracking.reports import box_ground_positions, forecast_residual_reports
from dronefl.wire import NoiseReportMessage, PredictionMessage, split_uplink

STEPS = 60


def test_a_reporting_drone_sends_the_reports_its_record_gives(tmp_path):
    scenario = load_scenario("case2")
    drone_id = 2  # sees two targets, each shared with another drone
    predictor = TrajectoryPredictor(
        build_model(PretrainSpec(scenario, "dronefl").model, seed=0), runtime="torch"
    )
    settings = DroneSettings("case2", drone_id, tmp_path / "model.npz", tmp_path, report_noise=True)
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
        if k < settings.past_steps - 1:  # no window yet: no predictions, no report
            assert message.target_ids == () and report == b""
        else:
            reports.append((k, NoiseReportMessage.decode(report)))
        world.step(np.zeros((len(scenario.drones), 2)))
    record = drone.record
    boxes = np.where(record.detected[:, :, None], record.boxes, np.nan)
    camera = PinholeCamera.from_spec(scenario.camera)
    ground = box_ground_positions(camera, boxes, record.odometry, scenario.vehicle.height / 2)
    expected = forecast_residual_reports(predictions, [ground])
    compared = 0
    for k, report in reports:
        assert report.drone_id == drone_id and report.step == k
        for target_id, noise in zip(report.target_ids, report.noise, strict=True):
            want = expected[k, 0, scenario.target_ids.index(target_id)]
            np.testing.assert_allclose(noise, want, rtol=2e-3, atol=1e-4)  # half floats
            compared += 1
    assert compared > 50


def test_split_uplink_without_a_report_and_with_a_short_payload():
    message = PredictionMessage(1, 3, (2,), np.ones((1, 1, 2))).encode()
    assert split_uplink(message) == (message, b"")
    assert split_uplink(b"\x02") == (b"\x02", b"")


def test_the_deployment_refuses_an_unknown_noise_split(tmp_path):
    from dronefl.deploy.cloud import CloudSettings
    from dronefl.deploy.launcher import DeployConfig

    with pytest.raises(ValueError, match="--noise-split"):
        DeployConfig(scenario="case2", out=tmp_path, noise_split="oracle")
    with pytest.raises(ValueError, match="--noise-split"):
        CloudSettings(scenario="case2", model="m.npz", out=str(tmp_path), noise_split="oracle")
