"""The RTS smoother over the Fuser's recorded history: filterpy and Stone Soup agree to 1e-9;
segments (track resets) are smoothed independently; smoothing lowers the error."""

import numpy as np
import pytest

from dronefl.tracking import Fuser, FusionConfig, PositionMeasurement, rts_smooth

DT = 0.2  # s
Q = 0.3  # m^2/s^3
R = np.array([[0.5, 0.1], [0.1, 0.8]])  # m^2


def _stream(n_steps=120, seed=3):
    """A vehicle on a gentle arc and one drone's noisy positions of it (m)."""
    rng = np.random.default_rng(seed)
    truth, z = [], []
    p = np.array([1.0, 2.0])
    for k in range(n_steps):
        p = p + DT * 0.8 * np.array([np.cos(0.02 * k), np.sin(0.02 * k)])
        truth.append(p)
        z.append(p + rng.multivariate_normal(np.zeros(2), R))
    return np.array(truth), np.array(z)


def _plain_fuser(z):
    """The paper's fusion with adaptation and gating off (a plain Kalman filter) over ``z``."""
    config = FusionConfig(method="paper", adaptive=False, gate=None, acceleration_psd=Q)
    fuser = Fuser([1], [1], config, initial_positions={1: np.array([1.0, 2.0])})
    fuser.method._noise[0][0].covariance = R.copy()  # the drone's known noise
    for k, position in enumerate(z):
        fuser.update((k + 1) * DT, [PositionMeasurement(1, 1, position)])
    return fuser


def test_smoother_matches_filterpy_rts_smoother():
    kalman = pytest.importorskip("filterpy.kalman")
    _, z = _stream()
    fuser = _plain_fuser(z)
    history = fuser.history(1)
    kf = kalman.KalmanFilter(dim_x=4, dim_z=2)
    kf.x, kf.P = history.mean[0].copy(), history.covariance[0].copy()
    kf.F = fuser.model.transition_matrix(DT)
    kf.Q = fuser.model.process_noise(np.zeros(4), DT)
    kf.H, kf.R = fuser.model.measurement_matrix, R
    means, covs, _, _ = kf.batch_filter(z)
    smoothed_x, smoothed_p, _, _ = kf.rts_smoother(means, covs)
    ours = fuser.smooth()[1]
    # Row 0 is the track's birth at t0; rows 1.. are the updates filterpy saw.
    np.testing.assert_allclose(history.mean[1:], means, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ours.mean[1:], smoothed_x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ours.covariance[1:], smoothed_p, rtol=0, atol=1e-9)


def test_smoother_matches_stone_soup_kalman_smoother():
    pytest.importorskip("stonesoup")
    from datetime import datetime, timedelta

    from stonesoup.models.measurement.linear import LinearGaussian
    from stonesoup.models.transition.linear import (
        CombinedLinearGaussianTransitionModel,
        ConstantVelocity,
    )
    from stonesoup.predictor.kalman import KalmanPredictor
    from stonesoup.smoother.kalman import KalmanSmoother
    from stonesoup.types.detection import Detection
    from stonesoup.types.hypothesis import SingleHypothesis
    from stonesoup.types.state import GaussianState
    from stonesoup.types.track import Track
    from stonesoup.updater.kalman import KalmanUpdater

    _, z = _stream()
    fuser = _plain_fuser(z)
    ours, born = fuser.smooth()[1], fuser.history(1)
    order = [0, 2, 1, 3]  # Stone Soup's (x, vx, y, vy) from our (x, y, vx, vy)
    transition = CombinedLinearGaussianTransitionModel([ConstantVelocity(Q), ConstantVelocity(Q)])
    measurement = LinearGaussian(ndim_state=4, mapping=(0, 2), noise_covar=R)
    predictor, updater = KalmanPredictor(transition), KalmanUpdater(measurement)
    start = datetime(2026, 1, 1)
    state = GaussianState(
        born.mean[0][order][:, None], born.covariance[0][np.ix_(order, order)], timestamp=start
    )
    track = Track()
    for k, position in enumerate(z):
        stamp = start + timedelta(seconds=(k + 1) * DT)
        prediction = predictor.predict(state, timestamp=stamp)
        detection = Detection(position[:, None], timestamp=stamp, measurement_model=measurement)
        state = updater.update(SingleHypothesis(prediction, detection))
        track.append(state)
    smoothed = KalmanSmoother(transition).smooth(track)
    theirs_mean = np.array([s.state_vector[:, 0] for s in smoothed])[:, order]
    theirs_cov = np.array([s.covar for s in smoothed])[:, order][:, :, order]
    np.testing.assert_allclose(ours.mean[1:], theirs_mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ours.covariance[1:], theirs_cov, rtol=0, atol=1e-9)


def test_smoothing_lowers_the_error_of_the_filtered_track():
    truth, z = _stream(n_steps=400, seed=8)
    fuser = _plain_fuser(z)
    filtered = fuser.history(1).mean[1:, :2]
    smoothed = fuser.smooth()[1].position[1:]
    filtered_mse = np.mean(((filtered - truth) ** 2).sum(axis=1))
    smoothed_mse = np.mean(((smoothed - truth) ** 2).sum(axis=1))
    assert smoothed_mse < 0.7 * filtered_mse
    assert np.trace(fuser.smooth()[1].covariance[200]) < np.trace(fuser.history(1).covariance[200])


def test_a_reset_track_is_smoothed_in_separate_segments():
    fuser = Fuser([1], [1], FusionConfig(reset_after=2), initial_positions={1: np.zeros(2)})
    for k in range(1, 6):
        fuser.update(k * DT, [PositionMeasurement(1, 1, np.array([0.01 * k, 0.0]))])
    for k in range(6, 12):  # a 50 m jump: two rejections, then the track restarts there
        fuser.update(k * DT, [PositionMeasurement(1, 1, np.array([50.0 + 0.01 * k, 0.0]))])
    history = fuser.history(1)
    assert fuser.resets == 1
    assert history.start.sum() == 2  # the birth at t0 and the reset
    reset = int(np.flatnonzero(history.start)[1])
    smoothed = rts_smooth(history)
    # The row before the reset ends its segment: smoothing leaves it at its filtered value.
    np.testing.assert_array_equal(smoothed.mean[reset - 1], history.mean[reset - 1])
    assert np.abs(smoothed.position[:reset, 0]).max() < 1.0  # nothing of the jump leaks back
    assert np.all(np.abs(smoothed.position[reset:, 0] - 50.0) < 1.0)


def test_history_records_prior_transition_and_posterior():
    fuser = Fuser([1, 2], [1], initial_positions={1: np.zeros(2)})
    assert fuser.history(2) is None
    fuser.update(DT, [PositionMeasurement(1, 1, np.array([0.1, 0.0]))])
    fuser.update(2 * DT, [])
    history = fuser.history(1)
    np.testing.assert_allclose(history.t, [0.0, DT, 2 * DT])
    np.testing.assert_array_equal(history.start, [True, False, False])
    np.testing.assert_array_equal(history.accepted, [0, 1, 0])
    f = fuser.model.transition_matrix(DT)
    np.testing.assert_allclose(history.prior_mean[1], f @ history.mean[0])
    np.testing.assert_allclose(history.transition[2], f)
    # Without a measurement the posterior is the prior.
    np.testing.assert_array_equal(history.mean[2], history.prior_mean[2])
    with pytest.raises(ValueError, match="record=False"):
        Fuser([1], [1], record=False).history(1)
