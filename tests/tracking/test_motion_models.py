"""Motion models: closed forms, Jacobians against finite differences, Stone Soup cross-check."""

import numpy as np
import pytest

from dronefl.config import load_scenario
from dronefl.settings import Setting
from dronefl.tracking import (
    RANDOM_WALK_VELOCITY_TIME_CONSTANT,
    Fuser,
    FusionConfig,
    PositionMeasurement,
    cloud_fusion,
)
from dronefl.tracking.fusion import TEMPORAL_KERNEL
from dronefl.tracking.models import ConstantVelocity, CoordinatedTurn, MeanRevertingVelocity


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


@pytest.mark.parametrize(("tau", "dt"), [(0.25, 0.2), (2.0, 0.2), (0.5, 3.0)])
def test_mean_reverting_velocity_matches_stone_soups_ornstein_uhlenbeck(tau, dt):
    from datetime import timedelta

    stonesoup = pytest.importorskip("stonesoup.models.transition.linear")
    axis = stonesoup.OrnsteinUhlenbeck(noise_diff_coeff=0.7, damping_coeff=1.0 / tau)
    ss_model = stonesoup.CombinedLinearGaussianTransitionModel([axis, axis])
    model = MeanRevertingVelocity(acceleration_psd=0.7, velocity_time_constant=tau)
    order = [0, 2, 1, 3]  # Stone Soup's (x, vx, y, vy) -> our (x, y, vx, vy)
    interval = timedelta(seconds=dt)
    x = np.array([1.0, 2.0, 0.5, -0.5])

    f_ss = ss_model.matrix(time_interval=interval)[np.ix_(order, order)]
    q_ss = ss_model.covar(time_interval=interval)[np.ix_(order, order)]

    np.testing.assert_allclose(model.jacobian(x, dt), f_ss, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(model.process_noise(x, dt), q_ss, rtol=1e-10, atol=1e-15)


def test_mean_reverting_velocity_becomes_constant_velocity_for_a_long_time_constant():
    # tau = 1e4 s: every term differs from constant velocity's by about dt / tau = 2e-5.
    slow, cv = MeanRevertingVelocity(1.0, velocity_time_constant=1e4), ConstantVelocity(1.0)
    x = np.array([0.0, 0.0, 1.0, 1.0])
    np.testing.assert_allclose(slow.jacobian(x, 0.2), cv.jacobian(x, 0.2), atol=1e-4)
    np.testing.assert_allclose(slow.process_noise(x, 0.2), cv.process_noise(x, 0.2), rtol=1e-4)
    with pytest.raises(ValueError, match="velocity_time_constant"):
        MeanRevertingVelocity(1.0, velocity_time_constant=0.0)


def test_a_coasting_mean_reverting_track_slows_down_and_a_constant_velocity_one_does_not():
    # A target driving east at 2 m/s, seen by one drone for 10 s, then by no one for 2 s.
    speeds = {}
    for motion in ("constant_velocity", "mean_reverting"):
        config = FusionConfig(method="paper", motion=motion, velocity_time_constant=0.25)
        fuser = Fuser([1], [1], config)
        for k in range(51):
            fuser.update(0.2 * k, [PositionMeasurement(1, 1, np.array([0.4 * k, 0.0]))])
        track = fuser.update(12.0, [])[1]
        speeds[motion] = float(np.linalg.norm(track.velocity))
    assert speeds["constant_velocity"] > 1.5  # carries the last velocity on
    assert speeds["mean_reverting"] < 1e-3  # 2 s = 8 time constants: e^-8 of it is left


def _filters(case: str, name: str = "recommended", **fusion):
    setting = Setting.load(name).with_values(fusion=fusion) if fusion else Setting.load(name)
    return cloud_fusion(setting.fusion, setting.drone.noise_reports, load_scenario(case))


def test_the_closed_loop_tracks_random_walk_targets_with_a_forgetting_velocity():
    # Case 2's vehicles walk at random; Cases 1 and 3 drive at constant speed.
    robust = _filters("case2")
    assert (robust.fusion.motion, robust.fusion.acceleration_psd) == ("mean_reverting", 1.0)
    assert robust.fusion.velocity_time_constant == RANDOM_WALK_VELOCITY_TIME_CONSTANT
    paper = _filters("case2", "paper").fusion  # the paper's EKF keeps CV
    assert (paper.motion, paper.acceleration_psd) == ("constant_velocity", 1.0)
    for case in ("case1", "case3"):
        config = _filters(case, "paper").fusion
        assert (config.motion, config.acceleration_psd) == ("constant_velocity", 0.1)


def test_the_constant_speed_q_acts_on_constant_speed_targets_only():
    for case in ("case1", "case3"):
        for method in ("robust", "paper"):
            config = _filters(case, "paper", method=method, constant_speed_psd=1e-3).fusion
            assert (config.motion, config.acceleration_psd) == ("constant_velocity", 1e-3)
    # random walk: its own q, whatever is asked
    assert _filters("case2", constant_speed_psd=1e-3) == _filters("case2", constant_speed_psd=0.1)


def test_the_planners_filter_and_the_kernel_are_for_random_walk_targets_only():
    case2 = _filters("case2")  # recommended: a second filter at q = 30, with the kernel
    assert case2.planner.acceleration_psd == 30.0 and case2.tracks is case2.planner
    assert case2.planner.temporal_kernel == TEMPORAL_KERNEL == case2.fusion.temporal_kernel
    assert case2.fusion.noise_split == "reported"
    one = _filters("case2", random_walk_planner_psd=None)
    assert one.planner is None and one.tracks is one.fusion
    for case in ("case1", "case3"):
        filters = _filters(case)
        assert filters.planner is None and filters.fusion.temporal_kernel is None
    assert _filters("case2", "paper").fusion.noise_split == "adaptive"


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
