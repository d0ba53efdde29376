"""The deployed episode's metrics: the world's truth joined with the cloud's log.

The metrics are those of ``dronefl track`` (:func:`dronefl.experiments.track.episode_metrics`
on the same :class:`~dronefl.experiments.track.EpisodeLog`), computed on the predictions the
cloud actually received, plus what only a deployment has: ``"engine": "deployment"``, the
silent steps and missed rounds of every drone, the controls the world did not get in time,
the wall time of every step against the 200 ms budget, the processes and their peak memory.
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np

from dronefl.config import Scenario
from dronefl.experiments.track import EpisodeLog, episode_metrics
from dronefl.io import atomic_savez

#: Wall-time budget of one step (the 5 Hz loop), ms.
STEP_BUDGET_MS = 200.0


def deployment_metrics(
    scenario: Scenario, world_npz: Path, cloud_npz: Path, cloud_json: Path, out: Path
) -> dict:
    """Metrics of one deployed episode; also writes ``<out>/episode.npz`` (as ``track``)."""
    with np.load(world_npz) as world, np.load(cloud_npz) as cloud:
        truth = {k: world[k] for k in world.files}
        logged = {k: cloud[k] for k in cloud.files}
    summary = json.loads(Path(cloud_json).read_text())
    n_steps = logged["cost"].shape[0]
    log = EpisodeLog(
        t=np.arange(n_steps + 1) * scenario.dt,
        target_position=truth["target_position"],
        drone_position=truth["drone_position"],
        drone_velocity=truth["drone_velocity"],
        prediction=logged["prediction"],
        track_position=logged["track_position"],
        trace=logged["trace"],
        cost=logged["cost"],
        fl_steps=[int(k) for k in logged["fl_steps"]],
    )
    arrays = {k: v for k, v in asdict(log).items() if isinstance(v, np.ndarray)}
    atomic_savez(out / "episode.npz", fl_steps=logged["fl_steps"], **arrays)
    metrics = episode_metrics(log, scenario)
    ids = scenario.drone_ids
    rounds = summary["fl_rounds"]
    # Steps whose wall time includes an FL round (the world waits for it) are not loop steps.
    round_steps = {int(r["step"]) - 1 for r in rounds}
    loop = np.array([ms for k, ms in enumerate(truth["step_ms"]) if k not in round_steps])
    metrics.update(
        {
            "engine": "deployment",
            "sim_seconds": n_steps * scenario.dt,
            "wall_seconds": float(truth["step_ms"].sum() / 1000),
            "fl_seconds": float(sum(r["seconds"] for r in rounds)),
            "planner_ms_per_step": summary["planner_ms_per_step"],
            "gating_rejections": summary["gating_rejections"],
            "track_resets": summary["track_resets"],
            "fl_rounds": rounds,
            "communication_kb_per_s": summary["communication_kb_per_s"],
            "telemetry_kb_per_s": summary["telemetry_kb_per_s"],
            "silent_steps": {str(d): int(logged["silent"][:, i].sum()) for i, d in enumerate(ids)},
            "late_predictions": summary["late_predictions"],
            "missed_rounds": {
                str(d): [r["round"] for r in rounds if d in r["missing"]] for d in ids
            },
            "missing_controls": {
                str(d): int(truth["missing_control"][:, i].sum()) for i, d in enumerate(ids)
            },
            "step_wall_ms": _distribution(loop),
            "cloud_step_ms": _distribution(logged["step_ms"][np.isfinite(logged["step_ms"])]),
            "realtime_margin": 1.0 - float(np.median(loop)) / STEP_BUDGET_MS if loop.size else None,
        }
    )
    metrics["realtime_factor"] = metrics["sim_seconds"] / metrics["wall_seconds"]
    return metrics


def _distribution(values: np.ndarray) -> dict[str, float]:
    """Median, 95th percentile and maximum, ms."""
    if values.size == 0:
        return {}
    return {
        "median": float(np.median(values)),
        "p95": float(np.percentile(values, 95)),
        "max": float(values.max()),
    }
