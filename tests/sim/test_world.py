"""World simulator: paths, motion models, drone dynamics, determinism."""

import numpy as np
import pytest

from dronefl.config import load_scenario
from dronefl.sim.pilot import PilotController
from dronefl.sim.targets import VehiclePath
from dronefl.sim.world import World


def test_vehicle_path_is_a_closed_loop_inside_the_field():
    scenario = load_scenario("case3")
    for spec in scenario.targets:
        path = VehiclePath(spec, scenario.field)
        assert np.allclose(path.points[0], path.points[-1])
        assert np.allclose(path.points[0], [spec.start_x, scenario.field.lane_y(spec.lane)])
        assert (path.points >= 0).all()
        assert (path.points <= [scenario.field.width, scenario.field.height]).all()


def test_constant_speed_vehicles_move_half_a_metre_per_second():
    world = World(load_scenario("case1"), seed=0)
    before = world.targets.position.copy()
    for _ in range(5):  # 1 s on a straight lane
        world.step(np.zeros((2, 2)))
    assert np.linalg.norm(world.targets.position - before, axis=1) == pytest.approx([0.5, 0.5])
    assert np.linalg.norm(world.targets.velocity, axis=1) == pytest.approx([0.5, 0.5])


def test_random_walk_perturbation_has_unit_std_and_is_redrawn_each_second():
    world = World(load_scenario("case2"), seed=3)
    draws = []
    for k in range(5 * 400):
        world.step(np.zeros((3, 2)))
        if k % 5 == 0:
            draws.append(world.targets.walk.copy())
    walk = np.concatenate(draws)  # (400 * 3, 2) draws of N(0, 1) m/s
    assert walk.std() == pytest.approx(1.0, abs=0.05)
    assert abs(walk.mean()) < 0.06
    # Held for exactly one second: five consecutive steps share one draw.
    world.step(np.zeros((3, 2)))
    held = world.targets.walk.copy()
    for _ in range(3):
        world.step(np.zeros((3, 2)))
        assert np.array_equal(world.targets.walk, held)


def test_drone_dynamics_respect_speed_accel_and_field_bounds():
    scenario = load_scenario("case1")
    world = World(scenario, seed=0)
    rng = np.random.default_rng(0)
    for _ in range(2000):
        previous = world.drones.velocity.copy()
        world.step(rng.normal(0.0, 20.0, size=(2, 2)))
        assert (np.linalg.norm(world.drones.velocity, axis=1) <= 3.0 + 1e-9).all()
        accel = np.linalg.norm(world.drones.velocity - previous, axis=1) / world.dt
        # At the field's edge the outward velocity is zeroed (a hard stop); elsewhere the
        # acceleration bound holds.
        at_edge = ((world.drones.position <= 0) | (world.drones.position >= [160, 120])).any(1)
        assert (accel[~at_edge] <= 2.0 + 1e-9).all()
        assert (world.drones.position >= 0).all()
        assert (world.drones.position <= [160.0, 120.0]).all()


def test_double_integrator_matches_closed_form():
    world = World(load_scenario("case1"), seed=0)
    p0 = world.drones.position.copy()
    u = np.array([[1.0, 0.0], [0.0, -0.5]])  # m/s^2, inside the bounds
    for _ in range(5):
        world.step(u)
    t = 1.0
    assert world.drones.position == pytest.approx(p0 + 0.5 * u * t**2)
    assert world.drones.velocity == pytest.approx(u * t)


def test_odometry_is_noisy_truth_in_the_documented_layout():
    world = World(load_scenario("case1"), seed=0)
    odo = np.array([o.vector for o in world.odometry()])
    assert odo.shape == (2, 12)
    truth = np.concatenate([world.drones.position, world.drones.altitude[:, None]], axis=1)
    assert np.abs(odo[:, :3] - truth).max() < 0.05 * 5


def test_same_seed_same_run_and_different_seed_different_run():
    def trace(seed):
        world = World(load_scenario("case2"), seed=seed)
        pilot = PilotController(world.rng("pilot"))
        for _ in range(100):
            world.step(pilot.control(world))
        return world.targets.position.copy(), np.array([o.vector for o in world.odometry()])

    a, b, c = trace(1), trace(1), trace(2)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])
