"""The benchmark's goals, its Table II (ours beside the paper's) and ``bench.md``.

Every function here reads the :class:`~dronefl.bench.results.BenchResults` that
:func:`dronefl.bench.run.run_bench` builds (or its :class:`~dronefl.bench.results.Benchmarks`)
and measures nothing.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable
from dataclasses import dataclass

from dronefl.bench.energy import (
    RPI5_INFERENCE,
    RPI5_TRAINING,
    EnergyEstimate,
    PowerFigure,
    estimate,
)
from dronefl.bench.results import (
    BenchFigure,
    Benchmarks,
    BenchResults,
    ClosedLoopFigure,
    CommFigure,
    Figure,
    GoalResult,
    SimulatorFigure,
)
from dronefl.bench.timing import UNITS


@dataclass(frozen=True)
class Goal:
    """Field ``key`` of benchmark ``figure`` (a :class:`Benchmarks` field) must be ``op``
    (``<=`` or ``>=``) ``limit`` ``unit``."""

    name: str
    figure: str
    key: str
    op: str
    limit: float
    unit: str

    def value(self, benchmarks: Benchmarks) -> float:
        """The measured value in ``unit``; NaN where it was not measured (no such figure, or
        no FL round for ``at_fl_period``)."""
        figure = getattr(benchmarks, self.figure)
        return math.nan if figure is None else getattr(figure, self.key)


#: Issue 6's goals (communication, predictor, detector, planner, closed loop) and the README's
#: earlier ones (training epoch, simulator).
GOALS: tuple[Goal, ...] = (
    Goal("DroneFL comm. per drone, one FL round per 100 s, fp32 weights", "dronefl_comm",
         "at_fl_period", "<=", 0.7, "KB/s"),
    Goal("DroneFL comm. per drone, one FL round per 100 s, fp16 weights", "dronefl_comm_fp16",
         "at_fl_period", "<=", 0.7, "KB/s"),
    Goal("predictor, one drone step (6 targets)", "predictor_inference", "median", "<=", 0.3,
         "ms"),
    Goal("local training, one epoch", "training_epoch", "median", "<=", 0.3, "s"),
    Goal("detector, one 640x640 frame", "detector", "median", "<=", 50.0, "ms"),
    Goal("planner, one Case 3 step", "planner", "median", "<=", 5.0, "ms"),
    Goal("Case 3 closed loop with DroneFL", "closed_loop", "realtime_factor", ">=", 20.0,
         "x real time"),
    Goal("simulator, Case 3 (slowest environment)", "simulator", "min", ">=", 200.0,
         "x real time"),
)  # fmt: skip
_OPS: dict[str, Callable[[float, float], bool]] = {"<=": operator.le, ">=": operator.ge}

#: The paper's Table II: (centralized on an RTX 5090, DroneFL on a Raspberry Pi 5).
PAPER_TABLE2: dict[str, tuple[str, str]] = {
    "comm": ("2.46e3", "1.56"),
    "inference_latency": ("0.63", "0.13 (Y.) + 0.01 (T.)"),
    "inference_energy": ("38.85", "0.78 (Y.) + 0.11 (T.)"),
    "training_latency": ("33.61", "1.76"),
    "training_energy": ("4499.03", "14.11"),
}


def fmt(value: float | None, digits: int = 3) -> str:
    """``value`` to ``digits`` significant digits (no exponent below 10^5); ``—`` for None."""
    if value is None or not math.isfinite(value):
        return "—"
    if abs(value) >= 10**digits:
        return f"{value:,.0f}"
    return f"{value:.{digits}g}"


def evaluate_goals(benchmarks: Benchmarks) -> tuple[GoalResult, ...]:
    """Each goal with the measured value and ``met`` (None where the value is missing)."""
    results = []
    for goal in GOALS:
        value = goal.value(benchmarks)
        results.append(
            GoalResult(
                goal=goal.name,
                target=f"{goal.op} {fmt(goal.limit)} {goal.unit}",
                value=value,
                unit=goal.unit,
                met=None if math.isnan(value) else _OPS[goal.op](value, goal.limit),
            )
        )
    return tuple(results)


#: Energy per call of (figure, device power): the detector, the predictor, a training epoch.
ENERGY_SOURCES: dict[str, tuple[str, PowerFigure]] = {
    "detector": ("detector", RPI5_INFERENCE),
    "predictor": ("predictor_inference", RPI5_INFERENCE),
    "training_epoch": ("training_epoch", RPI5_TRAINING),
}


def seconds(figure: BenchFigure | None) -> float | None:
    """Median of latency ``figure`` in s; None when it was not measured."""
    if figure is None:
        return None
    return figure.median * UNITS[figure.unit]


def energy_estimates(benchmarks: Benchmarks) -> dict[str, EnergyEstimate]:
    """Per-call energy estimates (J) of :data:`ENERGY_SOURCES` that were measured: median
    latency x the stated device power (:func:`dronefl.bench.energy.estimate`)."""
    return {
        name: estimate(seconds(getattr(benchmarks, figure)), power)
        for name, (figure, power) in ENERGY_SOURCES.items()
        if getattr(benchmarks, figure) is not None
    }


def _sum(label_a: str, a: float | None, label_b: str, b: float | None) -> str:
    """``a + b = a (label_a) + b (label_b)``, or ``—`` when either is missing."""
    if a is None or b is None:
        return "—"
    return f"{fmt(a + b)} = {fmt(a)} ({label_a}) + {fmt(b)} ({label_b})"


def _energy(results: BenchResults, name: str) -> float | None:
    """The reading (J) if RAPL gave one, else the estimate, else None."""
    figure = getattr(results.benchmarks, ENERGY_SOURCES[name][0])
    if figure is not None and figure.energy_reading is not None:
        return figure.energy_reading.joules
    estimated = results.energy.estimates.get(name)
    return None if estimated is None else estimated.joules


def table2(results: BenchResults) -> list[tuple[str, str, str, str, str, str]]:
    """Rows (metric, paper centralized, paper DroneFL, ours centralized, ours DroneFL, ours
    centralized image model: the paper's baseline, no detector)."""
    f = results.benchmarks
    comm_c = f.centralized_uplink.kb_per_s if f.centralized_uplink else None
    detector = seconds(f.detector)
    kind = "estimate" if not results.energy.rapl.available else "RAPL reading"
    ours_comm = (
        " / ".join(
            _comm_cell(comm, label)
            for comm, label in ((f.dronefl_comm, "fp32"), (f.dronefl_comm_fp16, "fp16"))
            if comm is not None
        )
        or "—"
    )
    return [
        (
            "Communication cost (KB/s per drone)",
            *PAPER_TABLE2["comm"],
            fmt(comm_c),
            ours_comm,
            fmt(comm_c),
        ),
        (
            "Infer. latency per sample (s)",
            *PAPER_TABLE2["inference_latency"],
            _sum("Y.", detector, "T. large", seconds(f.centralized_inference)),
            _sum("Y.", detector, "T.", seconds(f.predictor_inference)),
            fmt(seconds(f.image_inference)),
        ),
        (
            f"Infer. energy per sample (J, {kind})",
            *PAPER_TABLE2["inference_energy"],
            "—",
            _sum("Y.", _energy(results, "detector"), "T.", _energy(results, "predictor")),
            "—",
        ),
        (
            "Train. latency per epoch (s)",
            *PAPER_TABLE2["training_latency"],
            fmt(seconds(f.centralized_training_epoch)),
            fmt(seconds(f.training_epoch)),
            fmt(seconds(f.image_training_epoch)),
        ),
        (
            f"Train. energy per epoch (J, {kind})",
            *PAPER_TABLE2["training_energy"],
            "—",
            fmt(_energy(results, "training_epoch")),
            "—",
        ),
    ]


def _comm_cell(comm: CommFigure, label: str) -> str:
    """DroneFL's KB/s at one round per FL period (the episode's average in brackets)."""
    if math.isnan(comm.at_fl_period):
        return f"{fmt(comm.kb_per_s)} {label} (no FL round)"
    return f"{fmt(comm.at_fl_period)} {label} (episode: {fmt(comm.kb_per_s)})"


def _ratio(ratio: float | None) -> str:
    return "" if ratio is None else fmt(ratio, 3) + "x"


def figure_row(figure: Figure) -> tuple[str, str, str, str, str]:
    """(what, measured, threads, reference in the same run, ratio) of one figure."""
    match figure:
        case BenchFigure(reference=reference):
            measured = f"{fmt(figure.median)} {figure.unit} (p95 {fmt(figure.p95)})"
            ref = f"{reference.what}: {fmt(reference.median)} {figure.unit}" if reference else ""
            return figure.what, measured, str(figure.threads), ref, _ratio(figure.ratio)
        case SimulatorFigure():
            measured = ", ".join(f"{fmt(v)}x ({env})" for env, v in figure.per_environment.items())
            return figure.what, measured, str(figure.threads), "", ""
        case ClosedLoopFigure(reference=reference):
            measured = (
                f"{fmt(figure.realtime_factor)}x ({fmt(figure.realtime_factor_without_fl)}x "
                f"without the {figure.fl_rounds} FL rounds)"
            )
            ref = f"{reference.what}: {fmt(reference.realtime_factor)}x"
            return figure.what, measured, figure.threads, ref, _ratio(figure.ratio)
        case _:  # communication: an UplinkFigure or a CommFigure
            measured = f"{fmt(figure.kb_per_s)} {figure.unit}"
            if isinstance(figure, CommFigure) and not math.isnan(figure.at_fl_period):
                measured += f" ({fmt(figure.at_fl_period)} at one round per 100 s)"
            ref = f"paper: {fmt(figure.paper_kb_per_s)} {figure.unit}"
            return figure.what, measured, "", ref, ""


_TABLE2_NOTE = (
    "Y.: YOLO11n per 640x640 frame; T.: the transformer per drone step (6 targets). Ours on this"
    " CPU, one thread; our centralized T. is the large model on boxes and odometry; the image"
    " model is the paper's baseline (10 frames of 48 px and odometry per sample, no detector;"
    " the paper's learns from images on a GPU). Training: one epoch of {windows} windows for"
    " all. Communication: centralized = a JPEG frame and odometry per drone every step; DroneFL"
    " = at one FL round per 100 s (the episode's average in brackets)."
)


def _table(header: tuple[str, ...], rows: list[tuple[str, ...]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def markdown(results: BenchResults) -> str:
    """``bench.md``: machine, figures, goals, energy and Table II."""
    machine = results.machine
    v = machine.versions
    parts = [
        "# dronefl bench",
        "",
        f"{machine.cpu_model}, {machine.cores_visible} cores visible; torch {v['torch']}, "
        f"onnxruntime {v['onnxruntime']}, flwr {v['flwr']}, numpy {v['numpy']}. "
        f"{results.started}, {fmt(results.wall_seconds)} s in all.",
    ]
    load = machine.load_average
    if load.start and load.end:
        parts[-1] += (
            f" Load average (1 min, runnable processes on the {machine.cores_visible} cores):"
            f" {load.start[0]:g} at the start, {load.end[0]:g} at the end."
        )
    if results.quick:
        parts += ["", "**Quick run**: shrunk sizes, the figures are not representative."]
    figures = results.benchmarks
    parts += [
        "",
        "## Figures (ratio = reference time / our time)",
        "",
        _table(
            ("what", "measured (median, p95)", "threads", "reference in the same run", "ratio"),
            [figure_row(figure) for _, figure in figures.items()],
        ),
        "",
        "## Goals",
        "",
        _table(
            ("goal", "target", "measured", "met"),
            [
                (
                    g.goal,
                    g.target,
                    f"{fmt(g.value)} {g.unit}",
                    {True: "yes", False: "**no**", None: "not measured"}[g.met],
                )
                for g in results.goals
            ],  # fmt: skip
        ),
        "",
        "## Energy",
        "",
        f"RAPL: {results.energy.rapl.reason or 'available'}.",
        "",
        _table(
            ("per call", "latency (s)", "power (W)", "energy estimate (J)", "power source"),
            [
                (name, fmt(e.latency_s), fmt(e.watts, 2), fmt(e.joules), e.power_source)
                for name, e in results.energy.estimates.items()
            ],
        ),
        "",
        "Estimates are latency on this machine x the stated device power, not measurements. A"
        " Raspberry Pi 5's cores are slower than this machine's, so for a Pi 5 they are likely"
        " too low. The predictor uses the YOLO row's power: the paper's transformer row (0.11 J"
        " per 0.01 s) has a one-digit latency.",
        "",
        "## Table II (paper) beside ours",
        "",
        _table(
            (
                "metric",
                "paper: centralized (RTX 5090)",
                "paper: DroneFL (RPi 5)",
                "ours: centralized (this CPU, 1 thread)",
                "ours: DroneFL (this CPU, 1 thread)",
                "ours: centralized image model (this CPU, 1 thread)",
            ),
            table2(results),
        ),
        "",
        _TABLE2_NOTE.format(
            windows=figures.training_epoch.windows if figures.training_epoch else "the"
        ),
        "",
    ]
    return "\n".join(parts)


def summary_line(name: str, figure: Figure) -> str:
    """One line for the console after benchmark figure ``name`` was measured."""
    _, measured, threads, ref, ratio = figure_row(figure)
    line = f"{name}: {measured}"
    if threads:
        line += f" [threads: {threads}]"
    if ref:
        line += f"; {ref}"
    if ratio:
        line += f" (ratio {ratio})"
    return line
