"""What ``dronefl bench`` measures, as types: the figures, the goals and ``bench.json``.

Every benchmark returns :class:`Benchmarks` holding the figures it measured (a
:class:`BenchFigure` for a latency, other classes for speeds and communication);
:class:`BenchResults` is the whole run, written to ``bench.json`` by
:func:`dronefl.serialize.save_result` and read back by :func:`dronefl.serialize.load_result`.
Fields made with :func:`~dronefl.serialize.omitted_when_none` are carried by some figures only
and are absent from the JSON of the others.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

from dronefl.bench.energy import EnergyEstimate, EnergyReading, RaplStatus
from dronefl.bench.machine import MachineInfo
from dronefl.config import Environment
from dronefl.serialize import omitted_when_none


@dataclass(frozen=True)
class BenchFigure:
    """Latency samples: ``what`` was measured, the ``median`` and 95th percentile ``p95`` per
    call in ``unit`` (``s``, ``ms`` or ``us``) of ``samples`` timed calls on ``threads`` threads.

    Where a reference implementation was timed in the same run, its figure is ``reference`` and
    ``ratio`` = reference median / our median (> 1: ours is faster). The other fields only some
    figures carry: ``measurements_per_step`` fused per step (fusion); ``targets`` per drone step
    and the model's ``parameters`` (predictor; ``reference_parameters`` the reference model's);
    ``windows`` per epoch (training); ``other_runtimes``, our model timed on other runtimes
    (predictor); ``per_environment``, the same figure in each environment (detector, render);
    ``paper_ms``, the paper's figure (detector, ms); ``energy_reading`` per call where RAPL gave
    one.
    """

    what: str
    unit: str
    median: float
    p95: float
    samples: int
    threads: int
    measurements_per_step: float | None = omitted_when_none()
    reference: BenchFigure | None = omitted_when_none()
    ratio: float | None = omitted_when_none()
    targets: int | None = omitted_when_none()
    parameters: int | None = omitted_when_none()
    reference_parameters: int | None = omitted_when_none()
    windows: int | None = omitted_when_none()
    other_runtimes: dict[str, BenchFigure] | None = omitted_when_none()
    per_environment: dict[Environment, BenchFigure] | None = omitted_when_none()
    paper_ms: float | None = omitted_when_none()
    energy_reading: EnergyReading | None = omitted_when_none()


@dataclass(frozen=True)
class SimulatorFigure:
    """Simulator speed in ``unit`` ``x real time`` (simulated s per wall s): in each
    environment of ``per_environment``, ``min`` the slowest one's, over ``sim_seconds``
    simulated s each on ``threads`` threads."""

    what: str
    unit: str
    per_environment: dict[Environment, float]
    min: float
    sim_seconds: float
    threads: int


@dataclass(frozen=True)
class EpisodeSpeed:
    """The speed of one closed-loop episode (``what``): ``realtime_factor`` (x, simulated s per
    wall s) of the episode's loop and ``realtime_factor_without_fl`` without the wall time of
    its FL rounds; ``wall_seconds`` of the loop and ``fl_seconds`` of its ``fl_rounds`` rounds
    (s); ``planner_ms_per_step`` (ms); ``call_seconds`` (s) of the whole episode call (setup,
    Flower session, plots)."""

    what: str
    realtime_factor: float
    realtime_factor_without_fl: float
    wall_seconds: float
    fl_seconds: float
    fl_rounds: int
    planner_ms_per_step: float
    call_seconds: float


@dataclass(frozen=True)
class ClosedLoopFigure:
    """DroneFL's closed-loop episode in ``unit`` ``x real time``, with the fields of
    :class:`EpisodeSpeed`, the ``threads`` it used (in words), the ``reference`` episode with
    fixed models and ``ratio`` = reference wall s / DroneFL wall s."""

    what: str
    unit: str
    realtime_factor: float
    realtime_factor_without_fl: float
    wall_seconds: float
    fl_seconds: float
    fl_rounds: int
    planner_ms_per_step: float
    call_seconds: float
    threads: str
    reference: EpisodeSpeed
    ratio: float


@dataclass(frozen=True)
class EnvironmentUplink:
    """The centralized uplink in one environment: ``kb_per_s`` (KB/s) the mean over the
    ``drones`` (KB/s per drone id) of ``frames`` frames, ``mean_jpeg_kb`` the mean message
    (JPEG frame + odometry, KB)."""

    kb_per_s: float
    drones: dict[int, float]
    frames: int
    mean_jpeg_kb: float


@dataclass(frozen=True)
class UplinkFigure:
    """The centralized baseline's uplink per drone, ``kb_per_s`` in ``unit`` KB/s: the
    headline ``environment``'s figure of ``per_environment``; ``paper_kb_per_s`` the paper's
    (KB/s)."""

    what: str
    unit: str
    kb_per_s: float
    environment: Environment
    per_environment: dict[Environment, EnvironmentUplink]
    paper_kb_per_s: float


@dataclass(frozen=True)
class CommFigure:
    """DroneFL's communication per drone with ``weights_dtype`` weights, ``unit`` KB/s:
    ``kb_per_s`` over the episode; ``at_fl_period`` the same traffic with exactly one round per
    ``fl_period_s`` s (NaN: no round ran); ``fl_rounds`` in the episode and
    ``weights_kb_per_round`` (KB, NaN: no round); the mean over drones per message type
    ``by_type`` (``"up:predictions"``, ...) and the rate of each of the ``drones`` (KB/s per
    drone id); ``paper_kb_per_s`` the paper's (KB/s)."""

    what: str
    unit: str
    kb_per_s: float
    at_fl_period: float
    fl_period_s: float
    fl_rounds: int
    weights_kb_per_round: float
    by_type: dict[str, float]
    drones: dict[int, float]
    paper_kb_per_s: float
    weights_dtype: str


#: Any benchmark figure.
Figure = BenchFigure | SimulatorFigure | ClosedLoopFigure | UplinkFigure | CommFigure


@dataclass(frozen=True)
class Benchmarks:
    """The figures measured, by benchmark, in the order the benchmarks run; None (and absent
    from the JSON) where a benchmark did not run."""

    fusion: BenchFigure | None = omitted_when_none()
    planner: BenchFigure | None = omitted_when_none()
    simulator: SimulatorFigure | None = omitted_when_none()
    predictor_inference: BenchFigure | None = omitted_when_none()
    centralized_inference: BenchFigure | None = omitted_when_none()
    training_epoch: BenchFigure | None = omitted_when_none()
    centralized_training_epoch: BenchFigure | None = omitted_when_none()
    image_inference: BenchFigure | None = omitted_when_none()
    image_training_epoch: BenchFigure | None = omitted_when_none()
    detector: BenchFigure | None = omitted_when_none()
    render: BenchFigure | None = omitted_when_none()
    centralized_uplink: UplinkFigure | None = omitted_when_none()
    closed_loop: ClosedLoopFigure | None = omitted_when_none()
    dronefl_comm: CommFigure | None = omitted_when_none()
    dronefl_comm_fp16: CommFigure | None = omitted_when_none()

    def items(self) -> list[tuple[str, Figure]]:
        """(benchmark name, figure) of every figure measured, in order."""
        measured = [(f.name, getattr(self, f.name)) for f in fields(self)]
        return [(name, figure) for name, figure in measured if figure is not None]

    def merged(self, other: Benchmarks) -> Benchmarks:
        """These figures with those of ``other`` added (replacing any of the same name)."""
        return replace(self, **dict(other.items()))


@dataclass(frozen=True)
class GoalResult:
    """A goal judged: its name ``goal``, the ``target`` (e.g. ``<= 0.3 ms``), the measured
    ``value`` in ``unit`` (NaN: not measured) and whether it was ``met`` (None: not measured)."""

    goal: str
    target: str
    value: float
    unit: str
    met: bool | None


@dataclass(frozen=True)
class BenchEnergy:
    """Whether RAPL gave readings (``rapl``) and the per-call energy ``estimates`` by name
    (``detector``, ``predictor``, ``training_epoch``), latency x a stated device power."""

    rapl: RaplStatus
    estimates: dict[str, EnergyEstimate]


@dataclass(frozen=True)
class BenchSizes:
    """How much each benchmark measures.

    ``sim_seconds`` simulated s per environment in ``environments`` (simulator, frames);
    ``record_seconds`` of Case 3 recorded for the predictor's data, of which
    ``windows_per_target`` windows of each of drone 1's 6 targets are kept;
    ``inference_calls`` x ``inference_rounds`` timed predictor calls per model;
    ``training_rounds`` timed epochs per model; ``frames`` rendered per environment, spread
    over ``flight_seconds`` s of flight; ``cloud_steps`` fusion and planner steps;
    ``episode_seconds`` simulated s per closed-loop episode.
    """

    sim_seconds: float = 600.0
    environments: tuple[Environment, ...] = ("crop_field", "orchard")
    record_seconds: float = 600.0
    windows_per_target: int = 500
    inference_calls: int = 500
    inference_rounds: int = 5
    training_rounds: int = 5
    frames: int = 100
    flight_seconds: float = 600.0
    cloud_steps: int = 500
    episode_seconds: float = 600.0


@dataclass(frozen=True)
class BenchResults:
    """``bench.json``: format version ``schema``, whether the sizes were the ``quick`` ones, the
    ``scenario``'s name, when it ``started`` (local time) and the ``wall_seconds`` (s) so far;
    the ``groups`` run so far with their ``sizes``; the ``machine``; the figures
    (``benchmarks``), the ``energy`` and the ``goals`` judged on them."""

    schema: int
    quick: bool
    scenario: str
    started: str
    wall_seconds: float
    groups: tuple[str, ...]
    sizes: BenchSizes
    machine: MachineInfo
    benchmarks: Benchmarks
    energy: BenchEnergy
    goals: tuple[GoalResult, ...]
