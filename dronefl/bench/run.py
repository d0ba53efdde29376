"""``dronefl bench``: run the benchmarks, write ``bench.json`` and ``bench.md`` atomically.

The benchmarks come in groups that share their setup (recorded windows, rendered frames, a
closed-loop episode); ``only`` picks groups. :data:`FULL` are the real sizes (Case 3, 600 s
episodes: 80 s on two cores with the pretrained models cached, 1-2 min more to pretrain them);
:data:`QUICK` shrinks every size, all in about 15 s (the closed loop then runs 20 s episodes
without an FL round).
"""

from __future__ import annotations

# MuJoCo reads MUJOCO_GL at its first import; the vision benchmark's renderer sets it first.
import dronefl.bench.vision  # noqa: F401  # isort: skip

import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from rich.console import Console

from dronefl.bench import bandwidth, closed_loop, cloud, predictor, simulator, vision
from dronefl.bench.energy import EnergyMeter, rapl_meter, rapl_status
from dronefl.bench.machine import LoadAverage, load_average, machine_info
from dronefl.bench.report import energy_estimates, evaluate_goals, markdown, summary_line
from dronefl.bench.results import BenchEnergy, Benchmarks, BenchResults, BenchSizes
from dronefl.config import Scenario, load_scenario
from dronefl.io import atomic_write_text
from dronefl.serialize import save_result
from dronefl.settings import Setting

SCHEMA_VERSION = 1


class BenchError(ValueError):
    """Bad ``dronefl bench`` input, found before any benchmark runs."""


FULL = BenchSizes()
QUICK = replace(
    FULL,
    sim_seconds=10.0,
    record_seconds=60.0,
    windows_per_target=50,
    inference_calls=50,
    inference_rounds=2,
    training_rounds=2,
    frames=4,
    flight_seconds=20.0,
    cloud_steps=40,
    episode_seconds=20.0,
)


@dataclass(frozen=True)
class BenchContext:
    """What every benchmark group gets: the ``sizes``, the ``work`` folder for its files, the
    ``pretrained`` models' folder and an energy ``meter`` (None without RAPL)."""

    sizes: BenchSizes
    work: Path
    pretrained: Path
    meter: EnergyMeter | None
    scenario: Scenario
    setting: Setting


def _predictor(ctx: BenchContext) -> Benchmarks:
    s = ctx.sizes
    with tempfile.TemporaryDirectory(dir=ctx.work) as tmp:
        data, step = predictor.record_windows(
            ctx.scenario, Path(tmp), s.record_seconds, s.windows_per_target
        )
    inference = predictor.bench_inference(step, s.inference_calls, s.inference_rounds, ctx.meter)
    training = predictor.bench_training(data, s.training_rounds, ctx.meter)
    n_targets = int(step["boxes"].shape[1])
    image = predictor.bench_image(len(data), n_targets, s.inference_calls, s.training_rounds)
    return inference.merged(training).merged(image)


def _vision(ctx: BenchContext) -> Benchmarks:
    s = ctx.sizes
    frames = {
        env: vision.render_frames(ctx.scenario, env, s.frames, s.flight_seconds)
        for env in s.environments
    }
    detector = vision.bench_detector(frames, ctx.scenario.target_ids, ctx.meter)
    uplink = bandwidth.centralized_uplink(frames, ctx.scenario.rate_hz)
    return replace(detector, centralized_uplink=uplink)


#: Benchmark groups in the order they run (fast ones first).
GROUPS: dict[str, Callable[[BenchContext], Benchmarks]] = {
    "cloud": lambda ctx: cloud.bench_cloud(ctx.scenario, ctx.sizes.cloud_steps),
    "simulator": lambda ctx: simulator.bench_simulator(
        ctx.scenario, ctx.sizes.sim_seconds, ctx.sizes.environments
    ),
    "predictor": _predictor,
    "vision": _vision,
    "closed_loop": lambda ctx: closed_loop.bench_closed_loop(
        ctx.scenario,
        ctx.work / "closed_loop",
        ctx.sizes.episode_seconds,
        ctx.pretrained,
        ctx.setting,
    ),
}


def check_inputs(out: Path, only: Sequence[str] | None, pretrained: Path) -> tuple[str, ...]:
    """Validate before any work; returns the groups to run. Raises :class:`BenchError`."""
    out, pretrained = Path(out), Path(pretrained)
    if out.exists() and not out.is_dir():
        raise BenchError(f"--out: {out} is a file, not a folder")
    if pretrained.exists() and not pretrained.is_dir():
        raise BenchError(f"--pretrained: {pretrained} is a file, not a folder")
    groups = tuple(only) if only else tuple(GROUPS)
    unknown = [g for g in groups if g not in GROUPS]
    if unknown:
        raise BenchError(f"--only: unknown {', '.join(unknown)}; choose from {', '.join(GROUPS)}")
    return tuple(g for g in GROUPS if g in groups)


def run_bench(
    out: Path,
    quick: bool = False,
    only: Sequence[str] | None = None,
    pretrained: Path = Path("runs/pretrained"),
    progress: bool = True,
    sizes: BenchSizes | None = None,
    scenario: Scenario | None = None,
    setting: Setting | None = None,
) -> BenchResults:
    """Run the benchmark groups ``only`` (default: all) and write ``out/bench.json`` and
    ``out/bench.md``; returns what ``bench.json`` holds.

    ``quick`` uses :data:`QUICK` sizes (``sizes`` overrides both). Closed-loop episodes go to
    ``out/closed_loop/<method>/``; pretrained models are taken from (or trained into)
    ``pretrained``; the closed loop flies ``setting`` (default: the recommended one). One line
    per figure is printed to stderr as it is measured unless ``progress`` is False.
    """
    groups = check_inputs(out, only, pretrained)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sizes = sizes or (QUICK if quick else FULL)
    console = Console(stderr=True, quiet=not progress)
    scenario = scenario or load_scenario("case3")
    ctx = BenchContext(
        sizes, out, Path(pretrained), rapl_meter(), scenario, setting or Setting.load()
    )
    started, wall, load = time.strftime("%Y-%m-%d %H:%M:%S %Z"), time.perf_counter(), load_average()
    benchmarks = Benchmarks()
    for group in groups:
        with console.status(f"benchmark: {group} ..."):
            measured = GROUPS[group](ctx)
        for name, figure in measured.items():
            console.print(summary_line(name, figure), markup=False, highlight=False, soft_wrap=True)
        benchmarks = benchmarks.merged(measured)
        # Written after every group: an interrupted run keeps what it measured.
        results = BenchResults(
            schema=SCHEMA_VERSION,
            quick=quick,
            scenario=scenario.name,
            started=started,
            wall_seconds=time.perf_counter() - wall,
            groups=groups[: groups.index(group) + 1],
            sizes=sizes,
            machine=machine_info(LoadAverage(start=load, end=load_average())),
            benchmarks=benchmarks,
            energy=BenchEnergy(rapl_status(), energy_estimates(benchmarks)),
            goals=evaluate_goals(benchmarks),
        )
        save_result(out / "bench.json", results)
        atomic_write_text(out / "bench.md", markdown(results))
    return results
