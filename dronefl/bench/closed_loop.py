"""End to end: closed-loop episodes (Case 3 by default) with DroneFL and, as the reference,
fixed models.

Both episodes run in the same process, one after the other: orchard, projection detector, seed
0, in the recommended setting (an FL round every 100 s for DroneFL), models pretrained in the
crop field (cached under ``pretrained``). The speed is simulated seconds per wall second;
DroneFL's includes its Flower rounds (one Flower simulation engine, Ray with two workers of
one CPU, kept up for the episode). The same DroneFL episode gives DroneFL's communication per
drone with fp32 weights; a third episode, DroneFL with fp16 weights, gives it with fp16.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from time import perf_counter

from dronefl.bench.bandwidth import dronefl_comm
from dronefl.bench.results import Benchmarks, ClosedLoopFigure, EpisodeSpeed
from dronefl.config import Scenario
from dronefl.experiments.track import TrackConfig, run_episode
from dronefl.fl.simulation import backend_config
from dronefl.results.episode import EpisodeMetrics
from dronefl.settings import Setting


def speed(what: str, metrics: EpisodeMetrics, call_seconds: float) -> EpisodeSpeed:
    """The speed of episode ``what`` from its ``metrics``, ``call_seconds`` (s) the whole
    :func:`run_episode` call: real-time factor (x) with and without the FL rounds, wall
    seconds, FL seconds and rounds, planner ms per step."""
    return EpisodeSpeed(
        what=what,
        realtime_factor=metrics.realtime_factor,
        realtime_factor_without_fl=metrics.sim_seconds
        / (metrics.wall_seconds - metrics.fl_seconds),
        wall_seconds=metrics.wall_seconds,
        fl_seconds=metrics.fl_seconds,
        fl_rounds=len(metrics.fl_rounds),
        planner_ms_per_step=metrics.planner_ms_per_step,
        call_seconds=call_seconds,
    )


def bench_closed_loop(
    scenario: Scenario, out: Path, duration: float, pretrained: Path, setting: Setting
) -> Benchmarks:
    """Run the ``fixed``, ``dronefl`` and ``dronefl`` with fp16 weights episodes of ``scenario``
    in ``setting``, ``duration`` s into ``out/fixed``, ``out/dronefl``, ``out/dronefl_fp16``:

    * ``closed_loop``: DroneFL's real-time factor (x) over the episode's loop, with the fixed
      episode as reference and ``ratio`` = fixed wall time / DroneFL wall time;
      ``call_seconds`` is the whole :func:`run_episode` call (setup, Flower session, plots);
    * ``dronefl_comm`` / ``dronefl_comm_fp16``: DroneFL's KB/s per drone with fp32 / fp16
      weights (:func:`dronefl.bench.bandwidth.dronefl_comm`).
    """
    metrics, calls = {}, {}
    period = setting.learning.period
    runs = {"fixed": ("fixed", "float32"), "dronefl": ("dronefl", "float32"),
            "dronefl_fp16": ("dronefl", "float16")}  # fmt: skip
    for name, (method, dtype) in runs.items():
        config = TrackConfig(
            scenario=scenario,
            out=out / name,
            setting=setting.with_values(training={"weights_dtype": dtype}),
            method=method,
            duration=duration,
            pretrained=pretrained,
            progress=False,
            animate=False,
        )
        started = perf_counter()
        metrics[name] = run_episode(config)
        calls[name] = perf_counter() - started
    what = (
        f"{scenario.name} closed loop, orchard, projection detector, {duration:g} s, "
        f"DroneFL with an FL round every {period:g} s"
    )
    ours = speed(what, metrics["dronefl"], calls["dronefl"])
    fixed = speed("the same episode with fixed models (no FL)", metrics["fixed"], calls["fixed"])
    workers = backend_config()["init_args"]["num_cpus"]
    return Benchmarks(
        closed_loop=ClosedLoopFigure(
            **asdict(ours),
            unit="x real time",
            threads=f"1 (torch, ONNX Runtime); FL rounds: {workers} Ray workers of 1 CPU",
            reference=fixed,
            ratio=fixed.wall_seconds / ours.wall_seconds,
        ),
        dronefl_comm=dronefl_comm(metrics["dronefl"], period, "float32"),
        dronefl_comm_fp16=dronefl_comm(metrics["dronefl_fp16"], period, "float16"),
    )
