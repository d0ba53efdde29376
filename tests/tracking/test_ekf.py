"""The EKF: agreement with filterpy, NIS consistency, gating, Joseph-form covariance."""

import numpy as np
import pytest
from scipy.stats import chi2

from dronefl.tracking.ekf import CHI2_2DOF_99, ExtendedKalmanFilter
from dronefl.tracking.models import ConstantVelocity, CoordinatedTurn

filterpy_ekf = pytest.importorskip("filterpy.kalman")

DT = 0.2  # s


def _filterpy_twin(model, mean, cov, r):
    """filterpy's ExtendedKalmanFilter set up like ours; predict_x runs our f(x)."""

    class Twin(filterpy_ekf.ExtendedKalmanFilter):
        def predict_x(self, u=0):
            self.x = model.transition(self.x[:, 0], DT)[:, None]

    twin = Twin(dim_x=model.ndim, dim_z=2)
    twin.x = mean[:, None].copy()
    twin.P = cov.copy()
    twin.R = r
    return twin


@pytest.mark.parametrize("model", [ConstantVelocity(0.2), CoordinatedTurn(0.2, 0.05)])
def test_matches_filterpy_on_the_same_measurement_stream(model):
    # Prepare: a target driving a gentle arc, measured with noise; no gating, fixed R.
    rng = np.random.default_rng(7)
    mean, cov = model.initial(np.array([1.0, 2.0]), np.eye(2), speed_std=1.0)
    if isinstance(model, CoordinatedTurn):
        mean[2], cov[3, 3] = 0.5, 0.5  # start moving, heading roughly known
    r = np.array([[0.8, 0.1], [0.1, 0.5]])
    ours = ExtendedKalmanFilter(model, mean, cov, gate=None)
    twin = _filterpy_twin(model, mean, cov, r)
    h = model.measurement_matrix
    truth = np.array([1.0, 2.0])

    for k in range(200):
        truth = truth + DT * 0.5 * np.array([np.cos(0.01 * k), np.sin(0.01 * k)])
        z = truth + rng.multivariate_normal(np.zeros(2), r)
        # Execute: filterpy's predict uses F and Q set from our model at the prior mean.
        twin.F = model.jacobian(twin.x[:, 0], DT)
        twin.Q = model.process_noise(twin.x[:, 0], DT)
        twin.predict()
        twin.update(z[:, None], lambda x: h, lambda x: h @ x)
        ours.predict(DT)
        diagnostics = ours.update(z, r)

        # Assert: states, covariances and diagnostics agree to 1e-9.
        np.testing.assert_allclose(ours.mean, twin.x[:, 0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(ours.covariance, twin.P, rtol=0, atol=1e-9)
        np.testing.assert_allclose(diagnostics.innovation, twin.y[:, 0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(diagnostics.innovation_covariance, twin.S, rtol=0, atol=1e-9)
        np.testing.assert_allclose(diagnostics.gain, twin.K, rtol=0, atol=1e-9)
        assert diagnostics.nis == pytest.approx(twin.mahalanobis**2, abs=1e-9)


def _simulate_consistent(n_steps, seed, q=0.5, r=(0.6, 0.3)):
    """A CV truth driven by exactly the filter's Q, measured with exactly its R."""
    rng = np.random.default_rng(seed)
    model = ConstantVelocity(q)
    r = np.diag(r)
    mean, cov = model.initial(np.zeros(2), r, speed_std=1.0)
    truth = rng.multivariate_normal(mean, cov)
    f, noise = model.jacobian(truth, DT), model.process_noise(truth, DT)
    stream = []
    for _ in range(n_steps):
        truth = f @ truth + rng.multivariate_normal(np.zeros(4), noise)
        stream.append((truth, truth[:2] + rng.multivariate_normal(np.zeros(2), r)))
    return model, mean, cov, r, stream


def test_mean_nis_of_a_consistent_filter_lies_within_its_chi_square_bounds():
    n = 1000
    model, mean, cov, r, stream = _simulate_consistent(n, seed=3)
    ekf = ExtendedKalmanFilter(model, mean, cov, gate=None)
    nis, nees = [], []
    for truth, z in stream:
        ekf.predict(DT)
        nis.append(ekf.update(z, r).nis)
        err = truth - ekf.mean
        nees.append(err @ np.linalg.solve(ekf.covariance, err))
    # n * mean NIS ~ chi2(2n), n * mean NEES ~ chi2(4n): two-sided 99 % bounds.
    assert chi2.ppf(0.005, 2 * n) / n < np.mean(nis) < chi2.ppf(0.995, 2 * n) / n
    assert chi2.ppf(0.005, 4 * n) / n < np.mean(nees) < chi2.ppf(0.995, 4 * n) / n


def test_an_injected_outlier_is_gated_out_and_counted():
    model, mean, cov, r, stream = _simulate_consistent(60, seed=5)
    ekf = ExtendedKalmanFilter(model, mean, cov)
    for k, (_, z) in enumerate(stream):
        ekf.predict(DT)
        if k == 40:
            prior_mean, prior_cov = ekf.mean.copy(), ekf.covariance.copy()
            diagnostics = ekf.update(z + np.array([25.0, -10.0]), r)
            assert not diagnostics.accepted
            assert diagnostics.nis > CHI2_2DOF_99
            np.testing.assert_array_equal(diagnostics.gain, 0.0)
            np.testing.assert_array_equal(ekf.mean, prior_mean)
            np.testing.assert_array_equal(ekf.covariance, prior_cov)
        else:
            ekf.update(z, r)
    assert ekf.rejections == 1
    assert chi2.ppf(0.99, 2) == pytest.approx(CHI2_2DOF_99, rel=1e-12)


def test_joseph_update_keeps_the_covariance_symmetric_positive_definite():
    # Many very precise updates from a vague prior (gain near 1, P shrinking by 10 orders).
    model = ConstantVelocity(1e-6)
    mean, cov = model.initial(np.zeros(2), 1e4 * np.eye(2), speed_std=100.0)
    ekf = ExtendedKalmanFilter(model, mean, cov, gate=None)
    for _ in range(500):
        ekf.predict(DT)
        ekf.update(np.zeros(2), 1e-6 * np.eye(2))
    np.testing.assert_allclose(ekf.covariance, ekf.covariance.T, rtol=1e-12, atol=0)
    assert np.linalg.eigvalsh(ekf.covariance).min() > 0


def test_bad_inputs_raise_clear_errors():
    model = ConstantVelocity()
    with pytest.raises(ValueError, match="mean must have shape"):
        ExtendedKalmanFilter(model, np.zeros(3), np.eye(4))
    with pytest.raises(ValueError, match="finite"):
        ExtendedKalmanFilter(model, np.full(4, np.nan), np.eye(4))
    ekf = ExtendedKalmanFilter(model, np.zeros(4), np.eye(4))
    with pytest.raises(ValueError, match="dt >= 0"):
        ekf.predict(-0.1)
    with pytest.raises(ValueError, match=r"need z \(2,\)"):
        ekf.update(np.zeros(3), np.eye(2))
    with pytest.raises(ValueError, match="not positive definite"):
        ekf.update(np.zeros(2), -10 * np.eye(2))
