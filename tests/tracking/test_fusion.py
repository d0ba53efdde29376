"""Multi-drone fusion: prediction-only targets, births, sequential = batch, forecasts, errors."""

import numpy as np
import pytest

from dronefl.io import load_state, save_state
from dronefl.tracking.ekf import ExtendedKalmanFilter
from dronefl.tracking.fusion import Fuser, FusionConfig, PositionMeasurement

DT = 0.2  # s


def _m(drone, target, x, y):
    return PositionMeasurement(drone, target, np.array([x, y]))


def test_a_target_nobody_sees_is_only_predicted():
    fuser = Fuser([1, 2], [1], initial_positions={1: np.zeros(2), 2: np.array([5.0, 5.0])})
    fuser.update(DT, [_m(1, 1, 0.1, 0.0)])
    before = fuser.tracks[2]
    tracks = fuser.update(2 * DT, [_m(1, 1, 0.2, 0.0)])
    f = fuser.model.jacobian(before.mean, DT)
    q = fuser.model.process_noise(before.mean, DT)
    np.testing.assert_allclose(tracks[2].mean, f @ before.mean)
    np.testing.assert_allclose(tracks[2].covariance, f @ before.covariance @ f.T + q)
    assert (tracks[2].accepted, tracks[2].rejected) == (0, 0)
    assert tracks[1].accepted == 1


def test_a_track_is_born_at_the_mean_of_its_first_measurements():
    # Two drones with R = I: the mean of two positions has covariance I / 2.
    fuser = Fuser([7], [1, 2], FusionConfig(initial_noise_std=1.0, initial_speed_std=2.0))
    assert fuser.tracks == {}
    track = fuser.update(0.0, [_m(1, 7, 1.0, 2.0), _m(2, 7, 3.0, 4.0)])[7]
    np.testing.assert_allclose(track.position, [2.0, 3.0])
    np.testing.assert_allclose(track.position_covariance, 0.5 * np.eye(2))
    np.testing.assert_allclose(track.covariance[2:, 2:], 4.0 * np.eye(2))
    np.testing.assert_allclose(track.velocity, [0.0, 0.0])


def test_sequential_fusion_equals_one_stacked_update():
    # With adaptation off, fusing drones 1 and 2 one after the other equals a single Kalman
    # update with the stacked measurement [z1; z2] and block-diagonal R (closed form).
    config = FusionConfig(adaptive=False, gate=None)
    fuser = Fuser([1], [1, 2], config, initial_positions={1: np.array([0.0, 0.0])})
    prior = fuser.forecast(DT)
    p = prior.predicted_covariances[0]
    x = fuser.model.transition(fuser.tracks[1].mean, DT)
    z = np.array([0.5, -0.2, 0.1, 0.3])
    track = fuser.update(DT, [_m(2, 1, 0.1, 0.3), _m(1, 1, 0.5, -0.2)])[1]
    h = np.zeros((4, 4))
    h[0, 0] = h[1, 1] = h[2, 0] = h[3, 1] = 1.0
    r = np.eye(4)
    k = p @ h.T @ np.linalg.inv(h @ p @ h.T + r)
    np.testing.assert_allclose(track.mean, x + k @ (z - h @ x), atol=1e-12)
    np.testing.assert_allclose(track.covariance, (np.eye(4) - k @ h) @ p, atol=1e-12)


@pytest.mark.parametrize("motion", ["constant_velocity", "coordinated_turn"])
def test_forecast_trace_equals_predict_then_sequential_updates(motion):
    rng = np.random.default_rng(2)
    fuser = Fuser(
        [1, 2],
        [1, 2, 3],
        FusionConfig(motion=motion),
        initial_positions={1: np.zeros(2), 2: np.array([3.0, 1.0])},
    )
    for k in range(1, 30):  # let R adapt to different values per pair
        fuser.update(k * DT, [
            _m(i, j, *(rng.normal(0.1 * k, 0.3 * i, 2) + (0 if j == 1 else 3)))
            for i in (1, 2, 3) for j in (1, 2)
        ])  # fmt: skip
    forecast = fuser.forecast(DT)
    for j, subset in [(1, ()), (1, (2,)), (2, (1, 3)), (2, (1, 2, 3))]:
        track = fuser.tracks[j]
        ekf = ExtendedKalmanFilter(fuser.model, track.mean, track.covariance, gate=None)
        ekf.predict(DT)
        for i in subset:
            ekf.update(ekf.mean[:2], fuser.measurement_noise(i, j))
        assert forecast.trace_after(j, subset) == pytest.approx(np.trace(ekf.covariance), rel=1e-10)
    table = forecast.trace_table(0, [0, 1, 2])
    assert table.shape == (8,)
    assert table[0] == pytest.approx(np.trace(forecast.predicted_covariances[0]))
    assert np.all(np.diff(table[[0, 1, 3, 7]]) < 0)  # each extra drone lowers the trace


def test_a_lost_track_is_reset_after_consecutive_rejections():
    fuser = Fuser([1], [1], FusionConfig(reset_after=3), initial_positions={1: np.zeros(2)})
    for k in range(1, 4):
        fuser.update(k * DT, [_m(1, 1, 0.0, 0.0)])
    for k in range(4, 7):  # the target "jumps" 40 m: every measurement is gated out
        track = fuser.update(k * DT, [_m(1, 1, 40.0, 0.0)])[1]
    assert fuser.rejections == 3
    assert fuser.resets == 1
    np.testing.assert_allclose(track.position, [40.0, 0.0])
    track = fuser.update(7 * DT, [_m(1, 1, 40.1, 0.0)])[1]
    assert track.accepted == 1


def test_coordinated_turn_fusion_follows_a_turning_target():
    # A vehicle on a 10 m radius circle at 1 m/s, two drones with 0.3 m noise.
    rng = np.random.default_rng(4)
    fuser = Fuser([1], [1, 2], FusionConfig(motion="coordinated_turn", initial_noise_std=0.3))
    errors, turn_rates = [], []
    for k in range(600):
        angle = 0.1 * k * DT
        truth = 10.0 * np.array([np.sin(angle), 1.0 - np.cos(angle)])
        track = fuser.update(k * DT, [
            PositionMeasurement(i, 1, truth + rng.normal(0.0, 0.3, 2)) for i in (1, 2)
        ])[1]  # fmt: skip
        if k > 100:
            errors.append(np.sum((track.position - truth) ** 2))
            turn_rates.append(track.mean[4])
    assert np.sqrt(np.mean(errors)) < 0.3  # better than either drone alone
    assert np.mean(turn_rates) == pytest.approx(0.1, abs=0.01)  # rad/s


def test_non_finite_measurements_are_dropped_and_counted():
    fuser = Fuser([1], [1, 2], initial_positions={1: np.zeros(2)})
    track = fuser.update(DT, [_m(1, 1, np.nan, 0.0), _m(2, 1, 0.1, 0.0)])[1]
    assert fuser.dropped == 1
    assert track.accepted == 1


def test_bad_calls_raise_clear_errors():
    fuser = Fuser([1], [1], initial_positions={1: np.zeros(2)})
    with pytest.raises(ValueError, match="unknown id"):
        fuser.update(DT, [_m(9, 1, 0.0, 0.0)])
    with pytest.raises(ValueError, match="two measurements"):
        fuser.update(DT, [_m(1, 1, 0.0, 0.0), _m(1, 1, 0.1, 0.0)])
    fuser.update(DT, [])
    with pytest.raises(ValueError, match="before the last update"):
        fuser.update(0.0, [])
    with pytest.raises(ValueError, match="unknown target"):
        Fuser([1], [1], initial_positions={2: np.zeros(2)})
    with pytest.raises(ValueError, match="unique"):
        Fuser([1, 1], [1])


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("motion", "kalman"),
        ("acceleration_psd", 0.0),
        ("initial_noise_std", float("nan")),
        ("adaptation_rate", 1.5),
        ("gate", -1.0),
        ("reset_after", 0),
    ],
)
def test_fusion_config_names_the_bad_field(field, value):
    with pytest.raises(ValueError, match=field):
        FusionConfig(**{field: value})


@pytest.mark.parametrize("method", ["robust", "paper"])
def test_a_restored_fuser_goes_on_bit_identically(tmp_path, method):
    # A closed-loop checkpoint saves the fusion's state (its whole history stacked into
    # arrays) in a state file; a fresh Fuser restored from it must fuse, smooth and save
    # exactly as the original.
    rng = np.random.default_rng(0)
    config = FusionConfig(method=method, motion="mean_reverting", velocity_time_constant=0.25)
    original = Fuser([1, 2], [1, 2], config)

    def steps(fusers, ks):
        for k in ks:
            truth = np.array([0.5 * k * DT, 1.0]), np.array([3.0, -0.2 * k * DT])
            batch = [
                _m(i, j + 1, *(truth[j] + rng.normal(0, 0.3, 2)))
                for i in (1, 2)
                for j in (0, 1)
                if not (i == 2 and j == 1 and k % 7 < 3)  # gaps: births of no row, coasting
            ]
            for fuser in fusers:
                fuser.update((k + 1) * DT, batch)

    steps([original], range(40))
    save_state(tmp_path / "fuser.npz", original.state())
    copy = Fuser([1, 2], [1, 2], config)
    copy.restore(load_state(tmp_path / "fuser.npz"))
    steps([original, copy], range(40, 80))
    for j in (1, 2):
        a, b = original.history(j), copy.history(j)
        for name in ("t", "prior_mean", "prior_covariance", "transition", "mean", "covariance"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
        assert np.array_equal(a.start, b.start) and np.array_equal(a.accepted, b.accepted)
        assert np.array_equal(original.smooth()[j].mean, copy.smooth()[j].mean)
    assert original.rejections == copy.rejections and original.resets == copy.resets
    for j, track in original.tracks.items():
        assert np.array_equal(track.mean, copy.tracks[j].mean)
        assert np.array_equal(track.covariance, copy.tracks[j].covariance)
    np.testing.assert_array_equal(original.method.noise(), copy.method.noise())
