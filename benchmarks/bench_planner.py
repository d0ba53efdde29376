"""Time the cloud side of one DroneFL step on Case 3: fusion update and planner.

Run: ``.venv/bin/python benchmarks/bench_planner.py [--steps N] [--case case3]``. The targets drive
east along their lanes at their nominal speed (a stand-in for the simulator, so that only
fusion and planning are timed); every drone reports a noisy prediction (std 1 m) of each target
in its footprint; the drones fly the planner's accelerations. Prints ms per planner step (median
and 95th percentile; forecast + plan) and ms per fusion step / us per measurement (median),
single-threaded numpy. The default 500 steps (100 s) keep the eastbound targets in the field.
"""

from __future__ import annotations

import argparse
import os

# One BLAS thread: the arrays are tiny and the figure should not depend on the core count.
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import time  # noqa: E402

import numpy as np  # noqa: E402

from dronefl.config import load_scenario  # noqa: E402
from dronefl.planning import DroneFLPlanner, double_integrator_step  # noqa: E402
from dronefl.tracking import Fuser, PositionMeasurement  # noqa: E402
from dronefl.types import DroneState  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", default="case3", help="built-in scenario name or YAML path")
    parser.add_argument("--steps", type=int, default=500, help="planning steps to time")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if args.steps < 20:
        parser.error("--steps must be at least 20 (the first 10 are warm-up)")

    scenario = load_scenario(args.case)
    rng = np.random.default_rng(args.seed)
    dt = scenario.dt
    targets = np.array(
        [[t.start_x, scenario.field.lane_y(t.lane)] for t in scenario.targets], dtype=float
    )
    target_velocity = np.array(
        [[t.speed if t.heading == "east" else -t.speed, 0.0] for t in scenario.targets]
    )
    index = {t.id: k for k, t in enumerate(scenario.targets)}
    drones = [
        DroneState(
            d.id,
            np.array(d.start, dtype=float)
            if d.start is not None
            else targets[[index[j] for j in d.targets]].mean(axis=0),
            np.zeros(2),
            d.altitude,
        )
        for d in scenario.drones
    ]
    fuser = Fuser(scenario.target_ids, scenario.drone_ids)
    planner = DroneFLPlanner.from_scenario(scenario)
    half = planner.half_extent

    plan_s, update_s, n_updates = [], [], []
    for step in range(args.steps):
        t = (step + 1) * dt
        targets = targets + target_velocity * dt
        measurements = []
        for k, d in enumerate(drones):
            in_view = (np.abs(targets - d.position) <= half[k]).all(axis=1)
            for tid, seen in zip(scenario.target_ids, in_view, strict=True):
                if seen:
                    noisy = targets[index[tid]] + rng.normal(0.0, 1.0, 2)
                    measurements.append(PositionMeasurement(d.drone_id, tid, noisy))
        start = time.perf_counter()
        fuser.update(t, measurements)
        update_s.append(time.perf_counter() - start)
        n_updates.append(max(len(measurements), 1))
        start = time.perf_counter()
        plan = planner.plan(drones, fuser.forecast(dt))
        plan_s.append(time.perf_counter() - start)
        drones = [
            DroneState(
                d.drone_id,
                *double_integrator_step(d.position, d.velocity, plan.accelerations[d.drone_id], dt),
                d.altitude,
                plan.accelerations[d.drone_id],
            )
            for d in drones
        ]

    plan_ms = 1e3 * np.array(plan_s[10:])  # the first steps include numpy warm-up
    per_update_us = 1e6 * np.array(update_s[10:]) / np.array(n_updates[10:])
    print(
        f"scenario {scenario.name}: {len(drones)} drones, {len(targets)} targets, "
        f"{args.steps} steps, single-threaded"
    )
    print(
        f"planner (forecast + plan): median {np.median(plan_ms):.2f} ms/step, "
        f"p95 {np.percentile(plan_ms, 95):.2f} ms/step"
    )
    update_ms = 1e3 * np.array(update_s[10:])
    print(
        f"fusion update: median {np.median(update_ms):.2f} ms/step "
        f"({np.mean(n_updates[10:]):.1f} measurements/step, "
        f"median {np.median(per_update_us):.1f} us per measurement incl. predict)"
    )


if __name__ == "__main__":
    main()
