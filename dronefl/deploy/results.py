"""The deployed episode's results: the world's truth joined with the cloud's log.

:class:`DeploymentMetrics` is ``track``'s :class:`~dronefl.results.episode.EpisodeMetrics`
(the same tracking metrics, computed by :func:`~dronefl.results.episode.tracking_metrics`
on the predictions the cloud actually received) plus what only a deployment has:
``engine = "deployment"``, each round's participants and missing drones, the silent steps
and missed rounds of every drone, the controls the world did not get in time, the wall time
of a step against the 200 ms budget, and the processes and their peak memory.
:class:`CloudLog` is what the cloud writes (``cloud.json``) for it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dronefl.accounting import ByteCounter
from dronefl.config import Scenario
from dronefl.io import atomic_savez
from dronefl.results.episode import (
    REPORTS_NAME,
    ClosedLoopRound,
    EpisodeLog,
    EpisodeMetrics,
    tracking_metrics,
)
from dronefl.serialize import load_result, save_result
from dronefl.tracking import set_distances

#: Wall-time budget of one step (the 5 Hz loop), ms.
STEP_BUDGET_MS = 200.0
ENGINE = "deployment"


@dataclass(frozen=True)
class DeployedRound(ClosedLoopRound):
    """A round of the deployment: played after ``step`` steps; ``participants`` the drones
    whose update was averaged, ``missing`` those of the scenario whose update was not (dead,
    late or rejected). ``weight_bytes_down`` includes the new global model sent after it."""

    step: int = 0
    participants: tuple[int, ...] = ()
    missing: tuple[int, ...] = ()


@dataclass(frozen=True)
class TrafficCount:
    """Bytes of one (drone, direction, kind) as counted by the cloud."""

    drone_id: int
    direction: str
    kind: str
    n_bytes: int


@dataclass(frozen=True)
class CloudLog:
    """What the cloud knows of an episode (``cloud.json``; per-step arrays in ``cloud.npz``).

    ``wall_seconds`` of the episode; ``planner_ms_per_step`` in ms; ``rounds`` the FL rounds;
    ``late_predictions`` per drone: predictions that arrived after their step's deadline;
    ``traffic`` every byte count of the drone <-> cloud link (predictions as received,
    controls, labels and weights as sent); ``telemetry_bytes`` the world's telemetry;
    ``supernodes`` each drone's SuperNode id; ``settings`` the cloud's settings as given
    but the setting, which is ``setting`` (by section) named ``setting_name``.
    """

    wall_seconds: float
    planner_ms_per_step: float
    gating_rejections: int
    track_resets: int
    rounds: tuple[DeployedRound, ...]
    late_predictions: dict[int, int]
    traffic: tuple[TrafficCount, ...]
    telemetry_bytes: int
    supernodes: dict[int, int]
    settings: dict[str, str | float]
    setting_name: str
    setting: dict[str, dict]

    def save(self, path: Path) -> Path:
        return save_result(path, self)

    @classmethod
    def load(cls, path: Path) -> CloudLog:
        return load_result(cls, path)


@dataclass(frozen=True)
class StepTimes:
    """Wall time of a step, ms: median, 95th percentile and maximum (NaN: no steps)."""

    median: float
    p95: float
    max: float

    @classmethod
    def of(cls, values: np.ndarray) -> StepTimes:
        if values.size == 0:
            return cls(float("nan"), float("nan"), float("nan"))
        return cls(float(np.median(values)), float(np.percentile(values, 95)), float(values.max()))


@dataclass(frozen=True)
class DeploymentMetrics(EpisodeMetrics):
    """``metrics.json`` of ``dronefl deploy up``: :class:`EpisodeMetrics` plus

    ``engine`` (``deployment``); ``silent_steps`` per drone: steps whose prediction did not
    reach the cloud by the deadline; ``late_predictions`` per drone; ``missed_rounds`` per
    drone; ``missing_controls`` per drone: steps its autopilot held position; ``step_wall_ms``
    the wall time of a step of the loop (world publishes -> controls applied; FL round steps
    left out) and ``cloud_step_ms`` the cloud's share of it; ``realtime_margin`` =
    1 - median step / 200 ms; ``telemetry_kb_per_s`` the world's telemetry to the cloud;
    ``processes`` how many processes ran (None when unknown) and ``peak_memory_mb`` their
    summed resident memory at its peak, MiB.
    """

    fl_rounds: tuple[DeployedRound, ...]
    engine: str
    silent_steps: dict[int, int]
    late_predictions: dict[int, int]
    missed_rounds: dict[int, tuple[int, ...]]
    missing_controls: dict[int, int]
    step_wall_ms: StepTimes
    cloud_step_ms: StepTimes
    realtime_margin: float
    telemetry_kb_per_s: float
    processes: int | None
    peak_memory_mb: float | None


@dataclass(frozen=True)
class RunInfo:
    """What ran, as the launcher knows it (``processes``/``peak_memory_mb`` None if not)."""

    method: str
    seed: int
    environment: str
    config: dict[str, str | int | float | bool]
    processes: int | None = None
    peak_memory_mb: float | None = None


def deployment_metrics(
    scenario: Scenario, world_dir: Path, cloud_dir: Path, out: Path, run: RunInfo
) -> DeploymentMetrics:
    """Join ``world.npz`` and ``cloud.npz``/``cloud.json``; writes ``<out>/episode.npz`` and,
    for ``dronefl replay``, ``<out>/reports.npz`` (``noise`` ``(K, M, N, 2, 2)`` m^2: the noise
    report the cloud received with each prediction, NaN where none came)."""
    with (
        np.load(Path(world_dir) / "world.npz") as world,
        np.load(Path(cloud_dir) / "cloud.npz") as cloud,
    ):
        truth = {k: world[k] for k in world.files}
        logged = {k: cloud[k] for k in cloud.files}
    summary = CloudLog.load(Path(cloud_dir) / "cloud.json")
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
    log.save(Path(out) / "episode.npz")
    atomic_savez(Path(out) / REPORTS_NAME, noise=logged["noise"])
    ids = scenario.drone_ids
    rounds = summary.rounds
    sim_seconds = n_steps * scenario.dt
    # Steps whose wall time includes an FL round (the world waits for it) are not loop steps.
    round_steps = {r.step - 1 for r in rounds}
    loop = np.array([ms for k, ms in enumerate(truth["step_ms"]) if k not in round_steps])
    counter = ByteCounter()
    for c in summary.traffic:
        counter.add(c.drone_id, c.direction, c.kind, c.n_bytes)
    cloud_ms = logged["step_ms"][np.isfinite(logged["step_ms"])]
    return DeploymentMetrics(
        scenario=scenario.name,
        scenario_hash=scenario.content_hash,
        method=run.method,
        seed=run.seed,
        environment=run.environment,
        detector="projection",
        labels=str(summary.setting["learning"]["labels"]),
        tracking=tracking_metrics(log, scenario),
        set_distances=set_distances(log.target_position, log.track_position, scenario.dt),
        fl_rounds=rounds,
        communication=counter.rates(sim_seconds),
        sim_seconds=sim_seconds,
        wall_seconds=float(truth["step_ms"].sum() / 1000),
        fl_seconds=float(sum(r.seconds for r in rounds)),
        planner_ms_per_step=summary.planner_ms_per_step,
        gating_rejections=summary.gating_rejections,
        track_resets=summary.track_resets,
        centralized_inputs=None,
        config={
            **run.config,
            "scenario": scenario.name,
            "setting_name": summary.setting_name,
            "setting_values": summary.setting,
        },
        engine=ENGINE,
        silent_steps={d: int(logged["silent"][:, i].sum()) for i, d in enumerate(ids)},
        late_predictions=summary.late_predictions,
        missed_rounds={d: tuple(r.round for r in rounds if d in r.missing) for d in ids},
        missing_controls={d: int(truth["missing_control"][:, i].sum()) for i, d in enumerate(ids)},
        step_wall_ms=StepTimes.of(loop),
        cloud_step_ms=StepTimes.of(cloud_ms),
        realtime_margin=1.0 - float(np.median(loop)) / STEP_BUDGET_MS
        if loop.size
        else float("nan"),
        telemetry_kb_per_s=summary.telemetry_bytes / 1000 / sim_seconds,
        processes=run.processes,
        peak_memory_mb=run.peak_memory_mb,
    )
