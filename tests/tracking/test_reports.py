"""The drones' own noise reports: the forecast residual against the next detection, its
ground back-projection, its causality, and the fusion sharing two drones' R by the reports."""

import numpy as np
import pytest

from dronefl.config import load_scenario
from dronefl.models.online import OnboardRecord
from dronefl.sim.camera import PinholeCamera
from dronefl.tracking import Fuser, FusionConfig, PositionMeasurement
from dronefl.tracking.reports import (
    ForecastResidual,
    box_ground_positions,
    detected_now,
    forecast_residual_reports,
)

DT = 0.2  # s


def test_box_centres_back_project_to_the_points_that_made_them():
    scenario = load_scenario("case3")
    camera = PinholeCamera.from_spec(scenario.camera)
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-20, 20, (5, 2)), np.full(5, 0.75)])  # (5, 3) m
    pose = np.zeros(12)
    pose[:3], pose[8] = (3.0, -2.0, 40.0), 0.4  # position (m) and yaw (rad)
    uv, _ = camera.project(points, pose[:3], pose[8])
    boxes = np.column_stack([uv, np.full((5, 2), 0.01)])
    boxes[2] = np.nan  # not detected
    ground = box_ground_positions(camera, boxes[None], pose[None], ground_z=0.75)[0]
    assert np.allclose(np.delete(ground, 2, axis=0), np.delete(points[:, :2], 2, axis=0))
    assert np.isnan(ground[2]).all()


def test_the_reported_noise_converges_to_prediction_plus_detection_noise():
    # A drone predicts with N(0, 0.5^2) m per axis and detects with N(0, 0.1^2): its
    # residual's second moment is (0.25 + 0.01) I m^2.
    rng = np.random.default_rng(1)
    n = 20000
    truth = np.cumsum(rng.normal(0, 0.1, (n + 1, 1, 2)), axis=0)
    predictions = (truth[1:] + rng.normal(0, 0.5, (n, 1, 2)))[:, None]  # (K, M=1, N=1, 2)
    detected = [truth + rng.normal(0, 0.1, truth.shape)]
    _, reports = forecast_residual_reports(predictions, detected, rate=0.002)
    assert np.isnan(reports[0]).all()  # nothing to compare with yet
    final = reports[-1, 0, 0]
    assert final == pytest.approx(0.26 * np.eye(2), abs=0.026)


def test_a_report_uses_only_what_the_drone_knew_when_it_sent_it():
    rng = np.random.default_rng(2)
    predictions = rng.normal(0, 1, (50, 2, 3, 2))
    detected = [rng.normal(0, 1, (50, 3, 2)) for _ in range(2)]
    _, reports = forecast_residual_reports(predictions, detected)
    later = [d.copy() for d in detected]
    later[0][30:] += 5.0  # detections from step 30 on
    predictions_later = predictions.copy()
    predictions_later[30:] += 5.0  # predictions from step 30 on
    _, again = forecast_residual_reports(predictions_later, later)
    assert np.array_equal(reports[:30], again[:30], equal_nan=True)
    assert not np.allclose(reports[31:, 0], again[31:, 0])


def test_the_bias_correction_removes_a_constant_offset_and_keeps_causality():
    # Predictions off by (0.8, -0.3) m with N(0, 0.3^2) noise; detections unbiased
    # (N(0, 0.05^2)): the running mean converges to the offset, the corrected predictions
    # lose it, and the reports then measure the noise alone (0.09 + 0.0025 per axis).
    rng = np.random.default_rng(3)
    n, offset = 4000, np.array([0.8, -0.3])
    truth = np.cumsum(rng.normal(0, 0.1, (n + 1, 1, 2)), axis=0)
    raw = (truth[1:] + offset + rng.normal(0, 0.3, (n, 1, 2)))[:, None]
    detected = [truth + rng.normal(0, 0.05, truth.shape)]
    sent, reports = forecast_residual_reports(raw, detected, correct_bias=True)
    assert np.array_equal(sent[0], raw[0])  # nothing known yet: sent as predicted
    late = slice(n // 2, None)
    error = sent[late, 0, 0] - truth[1:][late, 0]
    assert np.abs(error.mean(axis=0)).max() < 0.05
    assert reports[-1, 0, 0] == pytest.approx(0.0925 * np.eye(2), abs=0.03)
    # The same with the drone's own loop: the bias it subtracts at step k is the EMA, from
    # zero, of the raw residuals z_i - g_{i+1} of steps i < k (the integrator form).
    residual = ForecastResidual(1)
    ema = np.zeros(2)
    for k in range(200):
        residual.observe(detected[0][k])
        if k > 0:
            ema += residual.rate * (raw[k - 1, 0, 0] - detected[0][k, 0] - ema)
        assert residual.bias()[0] == pytest.approx(ema, abs=1e-12)
        residual.predicted(raw[k, 0] - residual.bias())
    # Without the correction the predictions travel unchanged and the reports do not move.
    unchanged, plain = forecast_residual_reports(raw, detected)
    assert np.array_equal(unchanged, raw)
    assert not np.allclose(plain[-1], reports[-1])


def test_detected_now_reads_the_last_step_of_the_assigned_targets():
    # Drone 2 of Case 2 watches targets 1 and 2 of 1-3: the flags of its last step, in
    # that order, whatever it saw of target 3 or at earlier steps.
    scenario = load_scenario("case2")
    drone = scenario.drone(2)
    record = OnboardRecord(drone.id, drone.altitude, scenario.target_ids, drone.targets, 5, {})
    record.detected[:3] = [[True, True, True], [True, False, True], [False, True, False]]
    record.steps = 2
    assert detected_now(record).tolist() == [True, False]
    record.steps = 3
    assert detected_now(record).tolist() == [False, True]


def test_forecast_residual_refuses_a_bad_rate():
    with pytest.raises(ValueError, match="rate"):
        ForecastResidual(3, rate=0.0)


def test_the_split_shares_the_adapted_total_in_proportion_to_the_reports():
    config = FusionConfig(adaptive=False, noise_split="reported", initial_noise_std=1.0)
    fuser = Fuser([1], [1, 2, 3], config)
    small, large = np.diag([0.04, 0.02]), np.diag([1.0, 1.0])
    fuser.update(0.0, [PositionMeasurement(d, 1, np.zeros(2)) for d in (1, 2)])  # birth
    fuser.update(
        DT,
        [
            PositionMeasurement(1, 1, np.zeros(2), small),
            PositionMeasurement(2, 1, np.zeros(2), large),
        ],
    )
    total = 4.0  # tr R_1 + tr R_2 before: 2 + 2 m^2
    scale = total / (np.trace(small) + np.trace(large))
    assert fuser.measurement_noise(1, 1) == pytest.approx(small * scale)
    assert fuser.measurement_noise(2, 1) == pytest.approx(large * scale)
    # A target whose drones did not all report keeps its R; so does a lone drone.
    before = fuser.measurement_noise(3, 1)
    fuser.update(
        2 * DT,
        [PositionMeasurement(1, 1, np.zeros(2), small), PositionMeasurement(3, 1, np.zeros(2))],
    )
    assert fuser.measurement_noise(3, 1) == pytest.approx(before)
    fuser.update(3 * DT, [PositionMeasurement(3, 1, np.zeros(2), small)])
    assert fuser.measurement_noise(3, 1) == pytest.approx(before)


def test_reports_let_the_fusion_beat_the_better_of_two_drones_with_slow_errors():
    # Two drones whose errors are slow (AR(1), phi = 0.995 per step) with variances 1.0 and
    # 0.05 m^2 per axis: their disagreement measures only the sum of their noises.
    rng = np.random.default_rng(3)
    n, phi = 3000, 0.995
    truth = np.column_stack([0.5 * DT * np.arange(n), np.zeros(n)])
    errors = np.zeros((n, 2, 2))
    std = np.sqrt(np.array([1.0, 0.05]))[:, None]
    for k in range(1, n):
        errors[k] = phi * errors[k - 1] + np.sqrt(1 - phi**2) * std * rng.normal(size=(2, 2))
    reports = [np.eye(2) * v for v in (1.0, 0.05)]
    mse = {}
    for split in ("adaptive", "reported"):
        fuser = Fuser([1], [1, 2], FusionConfig(noise_split=split))
        fused = []
        for k in range(n):
            measurements = [
                PositionMeasurement(d, 1, truth[k] + errors[k, i], reports[i])
                for i, d in enumerate((1, 2))
            ]
            fused.append(fuser.update(k * DT, measurements)[1].position)
        mse[split] = float((((np.array(fused) - truth) ** 2).sum(axis=1))[500:].mean())
    best = float((errors[500:, 1] ** 2).sum(axis=1).mean())
    assert mse["reported"] < best < mse["adaptive"]


def test_the_reported_split_is_a_robust_fusion_setting():
    with pytest.raises(ValueError, match="noise_split.*robust"):
        FusionConfig(method="paper", noise_split="reported")
    with pytest.raises(ValueError, match="noise_split"):
        FusionConfig(noise_split="oracle")
