"""Simulator speed: simulated seconds per wall second, Case 3, projection detector, no file I/O.

Times the loop that recording and the closed loop run on every step: world step, every drone's
odometry and detections, the scripted pilot. One Python thread.
"""

from __future__ import annotations

from time import perf_counter

from dronefl.bench.results import Benchmarks, SimulatorFigure
from dronefl.config import Environment, Scenario
from dronefl.perception import make_detector
from dronefl.sim.pilot import PilotController
from dronefl.sim.world import World


def realtime_factor(scenario: Scenario, environment: Environment, duration: float) -> float:
    """Simulated seconds per wall-clock second over ``duration`` s of ``scenario``."""
    world = World(scenario, environment, seed=0)
    detector, pilot = make_detector("projection", world), PilotController(world.rng("pilot"))
    steps = int(duration * world.scenario.rate_hz)
    started = perf_counter()
    for _ in range(steps):
        world.odometry()
        for view in world.camera_views():
            detector.detect(view)
        world.step(pilot.control(world))
    return steps * world.dt / (perf_counter() - started)


def bench_simulator(
    scenario: Scenario, duration: float, environments: tuple[Environment, ...]
) -> Benchmarks:
    """``simulator``: ``scenario``'s real-time factor (x) in each of ``environments``,
    ``duration`` s each; ``min`` is the slowest environment's."""
    factors = {env: realtime_factor(scenario, env, duration) for env in environments}
    return Benchmarks(
        simulator=SimulatorFigure(
            what=f"{scenario.name} simulator + projection detector + scripted pilot, no file I/O",
            unit="x real time",
            per_environment=factors,
            min=min(factors.values()),
            sim_seconds=duration,
            threads=1,
        )
    )
