"""Motion models: closed forms, Jacobians against finite differences, Stone Soup cross-check."""

import numpy as np
import pytest

from dronefl.tracking.models import ConstantVelocity, CoordinatedTurn


def test_constant_velocity_matrices_match_the_closed_form():
    # Prepare: q = 2 m^2/s^3, dt = 0.5 s.
    model = ConstantVelocity(acceleration_psd=2.0)
    x = np.array([1.0, 2.0, 3.0, -4.0])

    # Execute
    f = model.jacobian(x, 0.5)
    q = model.process_noise(x, 0.5)

    # Assert: q dt^3/3 = 1/12, q dt^2/2 = 1/4, q dt = 1, on each axis; no cross-axis terms.
    np.testing.assert_allclose(model.transition(x, 0.5), [2.5, 0.0, 3.0, -4.0])
    np.testing.assert_allclose(f[:2, 2:], 0.5 * np.eye(2))
    expected = np.array([
        [1 / 12, 0, 1 / 4, 0],
        [0, 1 / 12, 0, 1 / 4],
        [1 / 4, 0, 1, 0],
        [0, 1 / 4, 0, 1],
    ])  # fmt: skip
    np.testing.assert_allclose(q, expected)
    np.testing.assert_allclose(model.velocity(x), [3.0, -4.0])


def test_constant_velocity_matches_stone_soup():
    stonesoup = pytest.importorskip("stonesoup.models.transition.linear")
    ss_model = stonesoup.CombinedLinearGaussianTransitionModel(
        [stonesoup.ConstantVelocity(0.3), stonesoup.ConstantVelocity(0.3)]
    )
    model = ConstantVelocity(acceleration_psd=0.3)
    # Stone Soup orders the state (x, vx, y, vy); ours is (x, y, vx, vy).
    order = [0, 2, 1, 3]
    dt = 0.2
    from datetime import timedelta

    f_ss = ss_model.matrix(time_interval=timedelta(seconds=dt))
    q_ss = ss_model.covar(time_interval=timedelta(seconds=dt))
    x = np.array([1.0, 2.0, 0.5, -0.5])
    np.testing.assert_allclose(model.jacobian(x, dt), f_ss[np.ix_(order, order)], atol=1e-15)
    np.testing.assert_allclose(model.process_noise(x, dt), q_ss[np.ix_(order, order)], atol=1e-15)


def _numerical_jacobian(model, x, dt, step=1e-6):
    cols = []
    for k in range(len(x)):
        e = np.zeros(len(x))
        e[k] = step
        cols.append((model.transition(x + e, dt) - model.transition(x - e, dt)) / (2 * step))
    return np.stack(cols, axis=1)


@pytest.mark.parametrize("omega", [0.3, -0.8, 2e-4, 5e-5, 0.0])
def test_coordinated_turn_jacobian_matches_finite_differences(omega):
    model = CoordinatedTurn()
    x = np.array([10.0, -3.0, 0.7, 0.4, omega])
    np.testing.assert_allclose(
        model.jacobian(x, 0.2), _numerical_jacobian(model, x, 0.2), atol=1e-7
    )


def test_coordinated_turn_moves_on_the_circle_and_is_continuous_at_zero_turn():
    model = CoordinatedTurn()
    # A quarter circle: v = 1 m/s, omega = pi/2 rad/s for 1 s from heading east -> radius 2/pi,
    # ending (2/pi, 2/pi) away, heading north.
    x = model.transition(np.array([0.0, 0.0, 1.0, 0.0, np.pi / 2]), 1.0)
    np.testing.assert_allclose(x, [2 / np.pi, 2 / np.pi, 1.0, np.pi / 2, np.pi / 2], atol=1e-12)
    # Just below the small-turn switch the expansion agrees with the exact arc.
    v, psi, omega, dt = 0.5, 1.0, 0.99e-4, 0.2
    below = model.transition(np.array([0.0, 0.0, v, psi, omega]), dt)
    end = psi + omega * dt
    exact = v / omega * np.array([np.sin(end) - np.sin(psi), np.cos(psi) - np.cos(end)])
    np.testing.assert_allclose(below[:2], exact, atol=1e-11)
    straight = model.transition(np.array([1.0, 1.0, 0.5, 0.0, 0.0]), 0.2)
    np.testing.assert_allclose(straight, [1.1, 1.0, 0.5, 0.0, 0.0])


def test_coordinated_turn_noise_is_symmetric_positive_semidefinite():
    q = CoordinatedTurn().process_noise(np.array([0.0, 0.0, 0.5, 0.7, 0.1]), 0.2)
    np.testing.assert_allclose(q, q.T)
    assert np.linalg.eigvalsh(q).min() > -1e-15


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_models_reject_bad_noise_levels(bad):
    with pytest.raises(ValueError, match="acceleration_psd"):
        ConstantVelocity(bad)
    with pytest.raises(ValueError, match="turn_rate_psd"):
        CoordinatedTurn(turn_rate_psd=bad)
