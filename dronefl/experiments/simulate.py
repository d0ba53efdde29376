"""Record a run with the scripted pilot: every drone's onboard log plus the ground truth.

``dronefl simulate`` calls :func:`simulate`; the offline FL experiment uses the recorded folder
as its data set. Files written to ``out`` (formats in :mod:`dronefl.logs`)::

    drone_<id>.npz  ground_truth.npz  summary.json  topdown.png
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import TypeAdapter

from dronefl.config import Environment, Scenario
from dronefl.logs import GroundTruth, OnboardLog
from dronefl.perception import make_detector
from dronefl.progress import progress_bar
from dronefl.serialize import save_result
from dronefl.sim.pilot import PilotController
from dronefl.sim.world import World
from dronefl.validation import check_duration, check_seeds


@dataclass(frozen=True)
class DroneSummary:
    """One drone of a recorded run: ``altitude`` m, its ``targets``, and the fraction of steps
    in which it detected them (``detection_rate``, over all its targets, and per target)."""

    drone_id: int
    altitude: float
    targets: tuple[int, ...]
    detection_rate: float
    detection_rate_per_target: dict[int, float]


@dataclass(frozen=True)
class RunSummary:
    """``summary.json`` of a recorded run: what was flown, ``steps`` of the scenario's rate,
    ``sim_seconds`` and ``wall_seconds`` (s), ``realtime_factor`` (x) and every drone's
    detection rates."""

    scenario: str
    environment: str
    seed: int
    detector: str
    steps: int
    sim_seconds: float
    wall_seconds: float
    realtime_factor: float
    drones: tuple[DroneSummary, ...]


def scenario_dict(scenario: Scenario) -> dict:
    """The scenario as plain JSON-able data (stored in every log's metadata)."""
    return TypeAdapter(Scenario).dump_python(scenario, mode="json")


def simulate(
    scenario: Scenario,
    *,
    environment: Environment | None = None,
    duration: float = 600.0,
    seed: int = 0,
    out: Path,
    detector: str = "projection",
    progress: bool = True,
    plot: bool = True,
) -> dict:
    """Fly the scenario for ``duration`` s under the :class:`PilotController` and record it.

    Returns the summary that is also written to ``out/summary.json``: ``sim_seconds``,
    ``wall_seconds``, ``realtime_factor`` and per drone the ``detection_rate`` (fraction of
    (step, assigned target) pairs with a detection) and ``detection_rate_per_target``.
    """
    check_duration(duration, scenario.dt)
    check_seeds([seed])
    world = World(scenario, environment, seed)
    det = make_detector(detector, world)
    pilot = PilotController(world.rng("pilot"))
    n_steps = int(round(duration * scenario.rate_hz))
    target_ids = world.targets.ids
    column = {int(i): j for j, i in enumerate(target_ids)}
    m, n = len(world.drones.ids), len(target_ids)

    t = np.zeros(n_steps)
    odometry = np.zeros((m, n_steps, 12))
    boxes = np.full((m, n_steps, n, 4), np.nan)
    detected = np.zeros((m, n_steps, n), dtype=bool)
    confidence = np.zeros((m, n_steps, n))
    target_pos, target_vel = np.zeros((n_steps, n, 2)), np.zeros((n_steps, n, 2))
    target_heading = np.zeros((n_steps, n))
    drone_pos, drone_vel = np.zeros((n_steps, m, 2)), np.zeros((n_steps, m, 2))

    started = time.perf_counter()
    with progress_bar(
        f"simulate {scenario.name} ({world.environment.kind})", n_steps, enabled=progress
    ) as advance:
        for k in range(n_steps):
            t[k] = world.t
            target_pos[k], target_vel[k] = world.targets.position, world.targets.velocity
            target_heading[k] = world.targets.heading
            drone_pos[k], drone_vel[k] = world.drones.position, world.drones.velocity
            for i, (odo, view) in enumerate(
                zip(world.odometry(), world.camera_views(), strict=True)
            ):
                odometry[i, k] = odo.vector
                for d in det.detect(view):
                    j = column[d.target_id]
                    boxes[i, k, j], detected[i, k, j] = d.box, True
                    confidence[i, k, j] = d.confidence
            world.step(pilot.control(world))
            advance()
    wall = time.perf_counter() - started

    meta = {
        "scenario": scenario_dict(scenario),
        "environment": world.environment.kind,
        "seed": seed,
        "rate_hz": scenario.rate_hz,
        "detector": detector,
    }
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    drones_summary = []
    for i, spec in enumerate(scenario.drones):
        assigned = np.isin(target_ids, spec.targets)
        OnboardLog(
            spec.id,
            spec.altitude,
            t,
            odometry[i].astype(np.float32),
            target_ids,
            assigned,
            boxes[i],
            detected[i],
            confidence[i],
            meta,
        ).save(out / f"drone_{spec.id}.npz")
        per_target = {tid: float(detected[i, :, column[tid]].mean()) for tid in spec.targets}
        drones_summary.append(
            DroneSummary(
                drone_id=spec.id,
                altitude=spec.altitude,
                targets=tuple(spec.targets),
                detection_rate=float(detected[i][:, assigned].mean()),
                detection_rate_per_target=per_target,
            )
        )
    truth = GroundTruth(
        t,
        target_ids,
        target_pos,
        target_vel,
        target_heading,
        world.drones.ids,
        drone_pos,
        drone_vel,
        world.drones.altitude,
        meta,
    )
    truth.save(out / "ground_truth.npz")
    summary = RunSummary(
        scenario=scenario.name,
        environment=world.environment.kind,
        seed=seed,
        detector=detector,
        steps=n_steps,
        sim_seconds=n_steps * scenario.dt,
        wall_seconds=wall,
        realtime_factor=n_steps * scenario.dt / max(wall, 1e-9),
        drones=tuple(drones_summary),
    )
    save_result(out / "summary.json", summary)
    if plot:
        from dronefl.report.topdown import plot_topdown

        plot_topdown(
            scenario,
            world.environment,
            world.camera,
            truth,
            out / "topdown.png",
            detection_rates={d.drone_id: d.detection_rate for d in drones_summary},
        )
    return summary


def format_summary(summary: RunSummary) -> str:
    """Plain-text table of a :func:`simulate` summary."""
    lines = [
        f"{summary.scenario} in {summary.environment} (seed {summary.seed}, "
        f"{summary.detector} detector): {summary.sim_seconds:.0f} s simulated in "
        f"{summary.wall_seconds:.1f} s ({summary.realtime_factor:.0f}x real time)",
        "drone  altitude  targets        detection rate",
    ]
    for d in summary.drones:
        lines.append(
            f"{d.drone_id:>5}  {d.altitude:>6.1f} m  "
            f"{json.dumps(list(d.targets)):<13}  {d.detection_rate:.3f}"
        )
    return "\n".join(lines)
