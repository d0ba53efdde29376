"""Simulator speed: simulated seconds per wall second, Case 3, projection detector.

Times the loop the recording and closed-loop experiments run on each step (world step, every
drone's odometry and detections, the scripted pilot), without any file I/O. Goal: >= 200x real
time. Run: ``python benchmarks/bench_sim.py [--duration 600]``.
"""

from __future__ import annotations

import argparse
import platform
import time

from dronefl.config import load_scenario
from dronefl.perception import make_detector
from dronefl.sim.pilot import PilotController
from dronefl.sim.world import World


def realtime_factor(case: str, environment: str, duration: float) -> float:
    """Simulated seconds per wall-clock second for ``duration`` s of ``case``."""
    world = World(load_scenario(case), environment, seed=0)
    detector, pilot = make_detector("projection", world), PilotController(world.rng("pilot"))
    steps = int(duration * world.scenario.rate_hz)
    started = time.perf_counter()
    for _ in range(steps):
        world.odometry()
        for view in world.camera_views():
            detector.detect(view)
        world.step(pilot.control(world))
    return duration / (time.perf_counter() - started)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=600.0, help="simulated seconds")
    args = parser.parse_args()
    print(f"CPU: {platform.processor() or platform.machine()}, 1 Python thread")
    for env in ("crop_field", "orchard"):
        factor = realtime_factor("case3", env, args.duration)
        print(f"case3 {env:10s} projection: {factor:6.0f}x real time (goal >= 200x)")


if __name__ == "__main__":
    main()
