"""Offline federated learning (paper Sec. V-B, Fig. 4 and Fig. 5) and the DroneFL ablation.

:func:`run_fl_offline` records a crop-field run of one case with the scripted pilot, then trains
every requested method for ``rounds`` rounds on it and writes into ``out``::

    data/                 the recorded run (drone_<id>.npz, ground_truth.npz, summary.json)
    <method>/             history.json + checkpoint.npz per round (resumable)
    results.json          per method: mean test MSE per round, final MSE, bytes per round
    fig5_case<N>.png      average test MSE vs round, log scale, every method
    table.md              final MSE and DroneFL's reduction against each baseline

Federated methods run on Flower's simulation engine (one Ray start per method); the
centralized upper bound trains the ``large`` model on all drones' pooled windows in the cloud,
E epochs per round, and is evaluated on each drone's test windows like the others.
:func:`run_altitude_study` is the paper's motivation study (Fig. 4) and
:func:`run_ablation` DroneFL without AdaIN and without relative positions on all cases.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dronefl.config import Scenario, load_scenario, parse_scenario
from dronefl.experiments.simulate import scenario_dict, simulate
from dronefl.fl.checkpoint import Checkpoint, CheckpointError, load_checkpoint, save_checkpoint
from dronefl.fl.methods import ABLATION_METHODS, FIG5_METHODS, METHODS
from dronefl.fl.records import FlSettings
from dronefl.fl.server_app import initial_state
from dronefl.fl.simulation import run_federated
from dronefl.io import atomic_write_json, atomic_write_text, crash_point
from dronefl.logs import load_run
from dronefl.models.model import build_model, count_parameters, describe
from dronefl.models.train import evaluate, train_local
from dronefl.models.windows import WindowSet, ground_truth_labels, split_windows
from dronefl.progress import progress_bar
from dronefl.report.fl_plots import plot_altitude, plot_fig5

#: Advances a progress bar by one finished round.
Advance = Callable[[int], None]

#: FL baselines DroneFL is compared against in the table.
BASELINES: tuple[str, ...] = ("fedavg", "fedprox", "fedper")


@dataclass(frozen=True)
class OfflineConfig:
    """One offline FL experiment: scenario ``case`` (1-3), ``rounds`` global rounds,
    ``seed`` (simulation, model initialisation, training), ``duration`` s of recorded flight,
    window ``stride`` (samples), FedProx ``proximal_mu``, the ``methods`` to train, whether to
    ``resume`` finished work in ``out``, progress bars, the number format of the weights
    on the wire (``weights_dtype``), local ``epochs`` per round, the cloud's ``aggregation``
    rule, the ``round_timeout`` s it waits for the drones and injected drone ``faults`` (see
    :class:`FlSettings`)."""

    case: int
    out: Path
    rounds: int = 50
    seed: int = 0
    duration: float = 600.0
    stride: int = 10
    proximal_mu: float = 0.01
    methods: tuple[str, ...] = FIG5_METHODS
    resume: bool = False
    progress: bool = True
    weights_dtype: str = "float32"
    epochs: int = 10
    aggregation: str = "mean"
    round_timeout: float = 3600.0
    faults: str = ""

    def __post_init__(self) -> None:
        if self.case not in (1, 2, 3):
            raise ValueError(f"--case: must be 1, 2 or 3, got {self.case}")
        if self.rounds < 1:
            raise ValueError(f"--rounds: must be >= 1, got {self.rounds}")
        unknown = [m for m in self.methods if m not in METHODS]
        if unknown:
            raise ValueError(f"--methods: unknown {unknown}; choose from {list(METHODS)}")
        if not self.duration > 0:
            raise ValueError(f"--duration: must be > 0 s, got {self.duration}")
        for method in self.methods:  # every FL setting is valid before any work starts
            self.settings(method, self.out / "data")

    def settings(self, method: str, run_dir: Path) -> FlSettings:
        return FlSettings(
            run_dir=str(run_dir),
            out_dir=str(self.out / method),
            method=method,
            rounds=self.rounds,
            stride=self.stride,
            proximal_mu=self.proximal_mu,
            seed=self.seed,
            resume=self.resume,
            weights_dtype=self.weights_dtype,
            epochs=self.epochs,
            aggregation=self.aggregation,
            round_timeout=self.round_timeout,
            faults=self.faults,
        )


def run_fl_offline(config: OfflineConfig, scenario: Scenario | None = None) -> dict:
    """Record the case (or ``scenario``), train every method, write results, figure, table."""
    started = time.perf_counter()
    scenario = scenario or load_scenario(f"case{config.case}")
    run_dir = config.out / "data"
    if not (config.resume and (run_dir / "ground_truth.npz").is_file()):
        simulate(
            scenario,
            environment="crop_field",
            duration=config.duration,
            seed=config.seed,
            out=run_dir,
            progress=config.progress,
            plot=False,
        )
    load_run(run_dir)  # a corrupt recording fails here, naming the file, before any training
    results_path = config.out / "results.json"
    results = {
        "case": config.case,
        "scenario": scenario.name,
        "rounds": config.rounds,
        "seed": config.seed,
        "duration_s": config.duration,
        "stride": config.stride,
        "epochs": config.epochs,
        "aggregation": config.aggregation,
        "proximal_mu": config.proximal_mu,
        "mse": "m^2, mean over windows, 5 future steps and both axes; averaged over drones",
        "methods": _earlier_methods(results_path) if config.resume else {},
    }
    for method in config.methods:
        settings = config.settings(method, run_dir)
        if not config.resume:
            shutil.rmtree(settings.out_dir, ignore_errors=True)
        elif method in results["methods"] and _finished_history(settings) is not None:
            continue  # finished earlier: keep its block (and its timing) as it was
        t0 = time.perf_counter()
        with progress_bar(
            f"case {config.case} {method}", config.rounds, config.progress
        ) as advance:
            history = _train_method(settings, advance)
        results["methods"][method] = summarize(history, settings, time.perf_counter() - t0, run_dir)
        atomic_write_json(results_path, results)
    results["wall_seconds_this_invocation"] = time.perf_counter() - started
    atomic_write_json(results_path, results)
    plot_fig5(results, config.out / f"fig5_case{config.case}.png", FIG5_METHODS)
    atomic_write_text(config.out / "table.md", comparison_table([results], FIG5_METHODS))
    return results


def _earlier_methods(results_path: Path) -> dict:
    """Method results of an earlier run in the same folder (kept when resuming, so that e.g.
    the ablation adds its methods beside Fig. 5's)."""
    if not results_path.is_file():
        return {}
    try:
        methods = json.loads(results_path.read_text())["methods"]
    except (OSError, ValueError, KeyError, TypeError):
        methods = None
    if not isinstance(methods, dict) or not all(
        isinstance(block, dict) and "final_test_mse" in block for block in methods.values()
    ):
        raise CheckpointError(f"{results_path}: corrupt results file; remove it or drop --resume")
    return methods


def _train_method(settings: FlSettings, advance: Advance) -> list[dict]:
    done = _finished_history(settings)
    if done is not None:
        advance(len(done))
        return done
    if settings.resume and settings.checkpoint_path.is_file():
        advance(
            load_checkpoint(
                settings.checkpoint_path,
                settings.history_path,
                settings.method,
                like=initial_state(settings),
            ).server_round
        )
    if settings.method_spec.federated:
        return run_federated(settings, on_round=lambda _: advance(1))
    return run_centralized(settings, on_round=lambda _: advance(1))


def _finished_history(settings: FlSettings) -> list[dict] | None:
    """The history of a resumed method that already finished all its rounds."""
    if not (settings.resume and settings.checkpoint_path.is_file()):
        return None
    checkpoint = load_checkpoint(
        settings.checkpoint_path,
        settings.history_path,
        settings.method,
        like=initial_state(settings),
    )
    return checkpoint.history if checkpoint.server_round >= settings.rounds else None


def drone_splits(settings: FlSettings) -> dict[int, tuple[WindowSet, WindowSet]]:
    """Every drone's chronological train/test windows, labelled by ground truth."""
    logs, truth = load_run(settings.run_dir)
    spec = settings.windows
    return {
        d: split_windows(log, ground_truth_labels(log, truth), spec)
        for d, log in sorted(logs.items())
    }


def run_centralized(
    settings: FlSettings, on_round: Callable[[dict], None] | None = None
) -> list[dict]:
    """The upper bound: the ``large`` model trained in the cloud on every drone's pooled
    training windows (E epochs per round), evaluated per drone on its test windows."""
    torch.set_num_threads(1)
    splits = drone_splits(settings)
    pooled = WindowSet.concat([train for train, _ in splits.values()])
    model = build_model(settings.model, seed=settings.seed)
    model.load_state_dict(initial_state(settings))
    offset, history = 0, []
    if settings.resume and settings.checkpoint_path.is_file():
        checkpoint = load_checkpoint(
            settings.checkpoint_path,
            settings.history_path,
            settings.method,
            like=model.state_dict(),
        )
        model.load_state_dict(checkpoint.state)
        offset, history = checkpoint.server_round, checkpoint.history
    for server_round in range(offset + 1, settings.rounds + 1):
        stats = train_local(model, pooled, settings.train_config(server_round, 0))
        test = {d: evaluate(model, test_set) for d, (_, test_set) in splits.items()}
        entry = {
            "round": server_round,
            "mean_test_mse": float(np.mean(list(test.values()))),
            "test_mse": {str(d): v for d, v in test.items()},
            "train_loss": {"cloud": stats.loss},
            "rejected": [],
            "bytes": {"down": {}, "up": {}},
        }
        crash_point(f"round-end:{server_round}")
        history.append(entry)
        save_checkpoint(
            settings.checkpoint_path,
            settings.history_path,
            Checkpoint(settings.method, server_round, model.state_dict(), history),
        )
        if on_round is not None:
            on_round(entry)
    return history


def summarize(history: list[dict], settings: FlSettings, seconds: float, run_dir: Path) -> dict:
    """The per-method block of ``results.json``."""
    method = settings.method_spec
    rounds = sorted(history, key=lambda h: h["round"])
    down = [sum(h["bytes"]["down"].values()) for h in rounds]
    up = [sum(h["bytes"]["up"].values()) for h in rounds]
    block = {
        "model": describe(settings.model),
        "variant": method.variant,
        "adain": method.adain,
        "relative": method.relative,
        "parameters": count_parameters(build_model(settings.model)),
        "mean_test_mse": [h["mean_test_mse"] for h in rounds],
        "final_test_mse": rounds[-1]["mean_test_mse"],
        "final_test_mse_per_drone": rounds[-1]["test_mse"],
        "bytes_down_per_round": down,
        "bytes_up_per_round": up,
        "rejected": {str(h["round"]): h["rejected"] for h in rounds if h["rejected"]},
        "wall_seconds": seconds,
    }
    if not method.federated:
        # The cloud gets every drone's onboard log once (boxes + odometry; the paper's
        # centralized baseline ships raw images, far more).
        block["upload_bytes_once"] = sum(p.stat().st_size for p in run_dir.glob("drone_*.npz"))
    return block


def reduction(dronefl: float, baseline: float) -> float:
    """DroneFL's MSE reduction against a baseline, % (positive = DroneFL better)."""
    return 100.0 * (baseline - dronefl) / baseline if baseline > 0 else math.nan


def comparison_table(all_results: list[dict], methods: tuple[str, ...]) -> str:
    """Markdown: final test MSE of ``methods`` per case, and DroneFL's % reduction."""
    methods = [m for m in methods if any(m in r["methods"] for r in all_results)]
    lines = [
        "Final average test MSE (m^2) after the last round; lower is better.",
        "",
        "| case | " + " | ".join(methods) + " |",
        "|---|" + "---|" * len(methods),
    ]
    for r in all_results:
        cells = [_fmt(r["methods"].get(m, {}).get("final_test_mse")) for m in methods]
        lines.append(f"| {r['case']} | " + " | ".join(cells) + " |")
    lines += ["", "DroneFL's MSE reduction against each method, %:", ""]
    others = [m for m in methods if m != "dronefl"]
    lines += ["| case | " + " | ".join(others) + " |", "|---|" + "---|" * len(others)]
    for r in all_results:
        mine = r["methods"].get("dronefl", {}).get("final_test_mse")
        cells = []
        for m in others:
            base = r["methods"].get(m, {}).get("final_test_mse")
            cells.append("" if mine is None or base is None else f"{reduction(mine, base):+.3f}")
        lines.append(f"| {r['case']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _fmt(value: float | None) -> str:
    if value is None:
        return ""
    return f"{value:.3g}"


def run_ablation(
    out: Path,
    rounds: int = 50,
    seed: int = 0,
    stride: int = 10,
    resume: bool = False,
    progress: bool = True,
) -> list[dict]:
    """DroneFL, DroneFL without AdaIN and without relative positions, on Cases 1-3.

    Writes ``out/case<N>/`` per case, ``out/ablation_case<N>.png`` and ``out/ablation.md``.
    With ``resume`` and the ``out`` of an earlier ``fl-offline`` run, each case's recorded
    data and finished ``dronefl`` run are reused and the ablation's results are added to its
    ``results.json``.
    """
    all_results = []
    for case in (1, 2, 3):
        config = OfflineConfig(
            case,
            out / f"case{case}",
            rounds,
            seed,
            stride=stride,
            methods=ABLATION_METHODS,
            resume=resume,
            progress=progress,
        )
        results = run_fl_offline(config)
        plot_fig5(results, out / f"ablation_case{case}.png", ABLATION_METHODS)
        all_results.append(results)
    atomic_write_text(out / "ablation.md", comparison_table(all_results, ABLATION_METHODS))
    return all_results


def altitude_scenario(altitude_2: float) -> Scenario:
    """Fig. 4's set-up: two drones, each over its own vehicle (same motion, opposite ends of
    the field, so different horizontal positions); drone 1 at 30 m, drone 2 at ``altitude_2``."""
    raw = scenario_dict(load_scenario("case1"))
    raw["name"] = f"altitude-{altitude_2:g}m"
    raw["description"] = "Fig. 4 motivation study"
    raw["drones"][1]["altitude"] = altitude_2
    return parse_scenario(raw, source=raw["name"])


def run_altitude_study(
    out: Path,
    rounds: int = 50,
    seed: int = 0,
    stride: int = 10,
    methods: tuple[str, ...] = ("fedavg",),
    resume: bool = False,
    progress: bool = True,
) -> dict:
    """Drone 1's test MSE per round when drone 2 flies at (almost) the same altitude (29.9 m
    vs 30 m; scenarios need distinct altitudes) or a different one (20 m). Writes
    ``out/altitude.json`` and ``out/fig4_altitude.png``."""
    study: dict = {"rounds": rounds, "seed": seed, "drone": 1, "curves": {}}
    for label, altitude in (("same altitude", 29.9), ("different altitude", 20.0)):
        config = OfflineConfig(
            1,
            out / label.replace(" ", "_"),
            rounds,
            seed,
            stride=stride,
            methods=methods,
            resume=resume,
            progress=progress,
        )
        results = run_fl_offline(config, altitude_scenario(altitude))
        for method, block in results["methods"].items():
            history = _history(config.settings(method, config.out / "data"))
            study["curves"][f"{method}, {label}"] = {
                "altitude_drone_2": altitude,
                "drone_1_test_mse": [h["test_mse"]["1"] for h in history],
                "final": block["final_test_mse_per_drone"]["1"],
            }
    atomic_write_json(out / "altitude.json", study)
    plot_altitude(study, out / "fig4_altitude.png")
    return study


def _history(settings: FlSettings) -> list[dict]:
    return load_checkpoint(settings.checkpoint_path, settings.history_path, settings.method).history
