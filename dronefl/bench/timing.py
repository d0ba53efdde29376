"""Timing helpers shared by every benchmark, and the latency figure they all return.

A latency is summarised as a :class:`~dronefl.bench.results.BenchFigure`: what was measured,
its unit, the median and 95th percentile of the samples, how many samples, the threads used and,
where a reference implementation was timed in the same run, the reference's figure and
``ratio = reference median / our median`` (> 1: ours is faster).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import replace
from time import perf_counter

import numpy as np

from dronefl.bench.results import BenchFigure

#: Seconds per unit of the figures' units.
UNITS: dict[str, float] = {"s": 1.0, "ms": 1e-3, "us": 1e-6}


def time_calls(fn: Callable[[], object], calls: int, warmup: int = 5) -> np.ndarray:
    """Wall seconds of each of ``calls`` calls of ``fn`` after ``warmup`` untimed ones."""
    if calls < 1:
        raise ValueError(f"calls must be >= 1, got {calls}")
    for _ in range(warmup):
        fn()
    seconds = np.empty(calls)
    for k in range(calls):
        started = perf_counter()
        fn()
        seconds[k] = perf_counter() - started
    return seconds


def time_interleaved(
    fns: Mapping[str, Callable[[], object]], calls: int, rounds: int, warmup: int = 5
) -> dict[str, np.ndarray]:
    """Per-call wall seconds of each function, ``rounds`` x ``calls`` samples each.

    The functions take turns, one round of ``calls`` each, so that a change of load on a shared
    machine hits ours and the reference alike.
    """
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    for fn in fns.values():
        for _ in range(warmup):
            fn()
    samples: dict[str, list[np.ndarray]] = {name: [] for name in fns}
    for _ in range(rounds):
        for name, fn in fns.items():
            samples[name].append(time_calls(fn, calls, warmup=0))
    return {name: np.concatenate(parts) for name, parts in samples.items()}


def latency(what: str, seconds: np.ndarray, unit: str, threads: int) -> BenchFigure:
    """The figure of latency samples ``seconds`` (s) of calls on ``threads`` threads, reported
    in ``unit`` (``s|ms|us``)."""
    seconds = np.asarray(seconds, dtype=float)
    if seconds.size == 0 or not np.isfinite(seconds).all():
        raise ValueError(f"{what}: needs finite samples, got {seconds.size}")
    scale = UNITS[unit]
    return BenchFigure(
        what=what,
        unit=unit,
        median=float(np.median(seconds)) / scale,
        p95=float(np.percentile(seconds, 95)) / scale,
        samples=int(seconds.size),
        threads=threads,
    )


def with_reference(figure: BenchFigure, reference: BenchFigure) -> BenchFigure:
    """``figure`` with ``reference`` (a figure in the same unit) and ``ratio`` = reference
    median / our median attached: how many times faster ours is."""
    if reference.unit != figure.unit:
        raise ValueError(f"reference unit {reference.unit} differs from {figure.unit}")
    return replace(figure, reference=reference, ratio=reference.median / figure.median)
