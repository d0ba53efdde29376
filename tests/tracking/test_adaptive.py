"""Adaptive measurement noise: one EMA step by hand, the floor, gating, convergence."""

import math

import numpy as np
import pytest

from dronefl.tracking.adaptive import (
    AdaptiveMeasurementNoise,
    floor_eigenvalues,
    truncated_second_moment,
)
from dronefl.tracking.ekf import UpdateDiagnostics
from dronefl.tracking.fusion import Fuser, FusionConfig, PositionMeasurement


def _diagnostics(y, hph, accepted=True):
    s = np.asarray(hph) + np.eye(2)
    return UpdateDiagnostics(
        np.asarray(y, float),
        s,
        np.asarray(hph, float),
        np.zeros((4, 2)),
        nis=0.0,
        accepted=accepted,
    )


def test_one_update_is_the_ema_of_the_innovation_sample():
    # R = (1 - beta) R + beta (y y^T - H P H^T) with R = I, beta = 0.5, y = (2, 0), HPH = I/2:
    # 0.5 I + 0.5 (diag(4, 0) - 0.5 I) = diag(2.25, 0.25).
    noise = AdaptiveMeasurementNoise(np.eye(2), beta=0.5, floor=1e-3)
    noise.observe(_diagnostics([2.0, 0.0], 0.5 * np.eye(2)))
    np.testing.assert_allclose(noise.covariance, np.diag([2.25, 0.25]))


def test_the_floor_keeps_r_positive_definite():
    # A tiny innovation against a large predicted covariance gives a negative sample.
    noise = AdaptiveMeasurementNoise(0.1 * np.eye(2), beta=0.9, floor=0.01)
    noise.observe(_diagnostics([0.0, 0.0], 5.0 * np.eye(2)))
    np.testing.assert_allclose(np.linalg.eigvalsh(noise.covariance), [0.01, 0.01])
    # The floor lifts only the eigenvalues below it and keeps the eigenvectors.
    m = np.array([[1.0, 1.0], [1.0, 1.0]])  # eigenvalues 0 and 2
    np.testing.assert_allclose(floor_eigenvalues(m, 0.5), [[1.25, 0.75], [0.75, 1.25]])


def test_rejected_updates_leave_r_unchanged():
    noise = AdaptiveMeasurementNoise(np.eye(2), beta=0.5, floor=1e-3)
    noise.observe(_diagnostics([30.0, 0.0], np.eye(2), accepted=False))
    np.testing.assert_array_equal(noise.covariance, np.eye(2))


def test_truncation_factor_of_the_99_percent_gate():
    # (2 - 11.21 * 0.01) / (2 * 0.99) at g = -2 ln 0.01 = 9.21.
    g = -2 * math.log(0.01)
    assert truncated_second_moment(g) == pytest.approx((2 - (g + 2) * 0.01) / 1.98, rel=1e-12)
    assert truncated_second_moment(200.0) == pytest.approx(1.0, rel=1e-12)


def test_adaptive_r_converges_toward_the_true_noise_of_each_drone():
    # Prepare: one target moving as the filter's motion model says (white acceleration of the
    # configured PSD), seen by a precise drone 1 and a noisy drone 2 with correlated errors;
    # both start from R = I. The paper's sequential method with the innovation form.
    rng = np.random.default_rng(11)
    true_r = {1: np.diag([0.25, 0.09]), 2: np.array([[4.0, 1.0], [1.0, 2.0]])}
    config = FusionConfig(method="paper", acceleration_psd=0.01, adaptation_rate=0.02)
    fuser = Fuser([1], [1, 2], config, initial_positions={1: np.zeros(2)})
    f, q = fuser.model.jacobian(np.zeros(4), 0.2), fuser.model.process_noise(np.zeros(4), 0.2)
    state = np.array([0.0, 0.0, 0.5, 0.2])
    estimates = {1: [], 2: []}

    # Execute: 800 s at 5 Hz.
    for k in range(1, 4001):
        state = f @ state + rng.multivariate_normal(np.zeros(4), q)
        fuser.update(0.2 * k, [
            PositionMeasurement(i, 1, rng.multivariate_normal(state[:2], true_r[i]))
            for i in (1, 2)
        ])  # fmt: skip
        if k > 2000:
            for i in (1, 2):
                estimates[i].append(fuser.measurement_noise(i, 1))

    # Assert: the time-averaged estimate is within 10 % of the truth (Frobenius norm).
    for i in (1, 2):
        mean_r = np.mean(estimates[i], axis=0)
        error = np.linalg.norm(mean_r - true_r[i]) / np.linalg.norm(true_r[i])
        assert error < 0.10, (i, mean_r)


def test_bad_settings_raise():
    with pytest.raises(ValueError, match="beta"):
        AdaptiveMeasurementNoise(np.eye(2), beta=0.0, floor=0.1)
    with pytest.raises(ValueError, match="floor"):
        AdaptiveMeasurementNoise(np.eye(2), beta=0.1, floor=-1.0)
    with pytest.raises(ValueError, match="initial R"):
        AdaptiveMeasurementNoise(np.eye(3), beta=0.1, floor=0.1)
