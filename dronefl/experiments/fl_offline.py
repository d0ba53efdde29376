"""Offline federated learning (paper Sec. V-B, Fig. 4 and Fig. 5) and the DroneFL ablation.

:func:`run_fl_offline` records a crop-field run of a scenario with the scripted pilot for every
seed, trains every requested method for ``rounds`` rounds on it and writes into ``out``::

    seed_<s>/data/        the recorded run of seed s (drone_<id>.npz, ground_truth.npz, ...)
    seed_<s>/<method>/    history.json + checkpoint.npz per round (resumable)
    results.json          :class:`OfflineResults`: per method and seed the test MSE per round
                          and the final one per drone; mean +- std over seeds
    fig5_<scenario>.png   average test MSE vs round, log scale, every method that was run
    table.md              final MSE (mean +- std), DroneFL's reduction against each method,
                          and DroneFL against `local` paired over the seeds, per drone

How a method trains is set by its ``training`` kind (:mod:`dronefl.fl.methods`):
``federated`` methods run on Flower's simulation engine (one Ray start per method and seed);
``pooled`` ones (``centralized``, ``centralized-small``) train on every drone's pooled training
windows in the cloud, E epochs per round; ``local`` trains one model per drone on its own
windows, never aggregated. All are evaluated on each drone's test windows after every round.
The seed sets the recording, the model initialisation and the training order.

:func:`run_altitude_study` is the paper's motivation study (Fig. 4) and :func:`run_ablation`
DroneFL without AdaIN and without relative positions on several scenarios.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from dronefl.config import Scenario, load_scenario, parse_scenario
from dronefl.experiments.simulate import scenario_dict, simulate
from dronefl.fl.checkpoint import Checkpoint, CheckpointError, load_checkpoint, save_checkpoint
from dronefl.fl.methods import ABLATION_METHODS, FIG5_METHODS, METHODS
from dronefl.fl.records import FlSettings, RoundRecord, fl_settings
from dronefl.fl.server_app import initial_state
from dronefl.fl.simulation import run_federated
from dronefl.io import atomic_write_json, atomic_write_text, crash_point
from dronefl.logs import load_run
from dronefl.models.model import build_model, count_parameters, describe
from dronefl.models.train import evaluate, train_local
from dronefl.models.windows import WindowSet, ground_truth_labels, split_windows
from dronefl.progress import progress_bar
from dronefl.report.fl_plots import plot_altitude, plot_fig5
from dronefl.report.paired import paired_comparison, paired_markdown
from dronefl.results.fl import Curve, MethodResult, OfflineResults, SeedResult
from dronefl.settings import Setting
from dronefl.validation import check_duration, check_seeds

#: Called with each finished round (e.g. to advance a progress bar).
OnRound = Callable[[RoundRecord], None]

#: The evaluation seeds (recordings, initialisations, training order). Settings were chosen
#: on recordings with seeds >= 10 only.
EVALUATION_SEEDS: tuple[int, ...] = (0, 1, 2, 3, 4)
#: The most rounds an offline run may ask for.
MAX_ROUNDS = 10000
#: The paper's three cases, the default scenarios of the ablation.
PAPER_CASES: tuple[str, ...] = ("case1", "case2", "case3")


@dataclass(frozen=True)
class OfflineConfig:
    """One offline FL experiment: ``scenario`` (a built-in name such as ``case3`` or a YAML
    path), every method of ``methods`` trained as ``setting`` says (its model and training
    sub-configs; default: the recommended setting) for ``rounds`` global rounds on a
    recording of ``duration`` s per seed of ``seeds`` (each: recording, model
    initialisation, training), with windows every ``stride`` samples (the paper's offline
    protocol, not a setting); whether to ``resume`` finished work in ``out``, progress bars,
    the ``round_timeout`` s the cloud waits for the drones and injected drone ``faults`` (see
    :class:`FlSettings`)."""

    scenario: str
    out: Path
    setting: Setting = field(default_factory=Setting.load)
    rounds: int = 50
    seeds: tuple[int, ...] = EVALUATION_SEEDS
    duration: float = 600.0
    stride: int = 10
    methods: tuple[str, ...] = FIG5_METHODS
    resume: bool = False
    progress: bool = True
    round_timeout: float = 3600.0
    faults: str = ""

    def __post_init__(self) -> None:
        if not 1 <= self.rounds <= MAX_ROUNDS:
            raise ValueError(f"--rounds: must be in [1, {MAX_ROUNDS}], got {self.rounds}")
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"--seeds: need distinct seeds, got {list(self.seeds)}")
        check_seeds(self.seeds, "--seeds")
        unknown = [m for m in self.methods if m not in METHODS]
        if unknown:
            raise ValueError(f"--methods: unknown {unknown}; choose from {list(METHODS)}")
        check_duration(self.duration, 1.0)
        if not 1 <= self.stride <= 1000:
            raise ValueError(f"--stride: must be in [1, 1000], got {self.stride}")

    def seed_dir(self, seed: int) -> Path:
        return self.out / f"seed_{seed}"

    def settings(self, method: str, seed: int, scenario: Scenario) -> FlSettings:
        """The FL settings of ``method`` for ``seed``."""
        return fl_settings(
            self.setting, method, run_dir=str(self.seed_dir(seed) / "data"),
            out_dir=str(self.seed_dir(seed) / method), rounds=self.rounds, future_steps=5,
            stride=self.stride, seed=seed, field_m=(scenario.field.width, scenario.field.height),
            resume=self.resume, round_timeout=self.round_timeout, faults=self.faults,
        )  # fmt: skip


def run_fl_offline(config: OfflineConfig, scenario: Scenario | None = None) -> OfflineResults:
    """Record the scenario for every seed, train every method, write results, figure, table."""
    scenario = scenario or load_scenario(config.scenario)
    for method in config.methods:  # every FL setting is valid before any work starts
        config.settings(method, config.seeds[0], scenario)
    results_path = config.out / "results.json"
    results = OfflineResults(
        scenario.name,
        config.setting.name,
        config.setting.digest(),
        config.rounds,
        config.duration,
        config.stride,
    )
    if config.resume and results_path.is_file():
        earlier = OfflineResults.load(results_path)
        if _experiment(earlier) != _experiment(results):
            raise CheckpointError(
                f"{results_path}: results of another experiment ({earlier.scenario}, "
                f"setting {earlier.setting}, {earlier.rounds} rounds, {earlier.duration_s:g} s, "
                f"stride {earlier.stride}); use another --out"
            )
        results = replace(results, methods=dict(earlier.methods))
    for seed in config.seeds:
        record(config, scenario, seed)
        for method in config.methods:
            settings = config.settings(method, seed, scenario)
            if not config.resume:
                shutil.rmtree(settings.out_dir, ignore_errors=True)
            _claim(settings)
            if config.resume and _finished(settings) is not None and _seed_file(settings).is_file():
                done = _load_seed_result(settings, config)
            else:
                started = time.perf_counter()
                label = f"{scenario.name} seed {seed} {method}"
                with progress_bar(label, config.rounds, config.progress) as advance:
                    history = train_method(settings, advance)
                done = SeedResult.of(seed, history, time.perf_counter() - started)
                atomic_write_json(_seed_file(settings), _seed_json(done, config, settings))
            results.methods[method] = _block(results, settings).with_seed(done)
            results.save(results_path)
    if config.resume:
        results = _gather(config, scenario, results)
    results.save(results_path)
    ran = {m: results.methods[m].curve for m in results.methods}
    plot_fig5(ran, f"{scenario.name}, seeds {_seeds(config.seeds)}", _fig5_path(config, scenario))
    atomic_write_text(config.out / "table.md", comparison_table([results], tuple(results.methods)))
    return results


def _experiment(results: OfflineResults) -> tuple:
    """What must agree for results to belong to one experiment."""
    return (
        results.scenario,
        results.setting_digest,
        results.rounds,
        results.duration_s,
        results.stride,
    )


def _block(results: OfflineResults, settings: FlSettings) -> MethodResult:
    """The results block of ``settings.method`` so far (a fresh one if none)."""
    return results.methods.get(settings.method) or MethodResult(
        settings.method,
        describe(settings.model),
        count_parameters(build_model(settings.model)),
        settings.method_spec.training,
    )


def _seed_file(settings: FlSettings) -> Path:
    """Where one finished (method, seed) run keeps its :class:`SeedResult`."""
    return Path(settings.out_dir) / "result.json"


def _settings_file(settings: FlSettings) -> Path:
    """Where a (method, seed) folder records the settings it trains with."""
    return Path(settings.out_dir) / "settings.json"


def _claim(settings: FlSettings) -> None:
    """Record the settings ``settings.out_dir`` trains with; resuming, first refuse a folder
    that recorded other ones, so that a checkpoint or result of another setting (say another
    ``training.epochs`` into the same ``--out``) is never continued or reported as this one. A
    folder without recorded settings keeps only the setting and rounds check."""
    path = _settings_file(settings)
    if settings.resume and path.is_file():
        try:
            recorded = json.loads(path.read_text())
        except (OSError, ValueError):
            raise CheckpointError(f"{path}: corrupt settings; remove the folder") from None
        _refuse_other(path, recorded, settings.training_key())
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(path, settings.training_key())


def _refuse_other(path: Path, recorded: object, asked: dict) -> None:
    """Raise :class:`CheckpointError` naming every setting in which ``recorded`` (read from
    ``path``) differs from ``asked``."""
    if not isinstance(recorded, dict):
        raise CheckpointError(f"{path}: corrupt settings; remove the folder")
    differ = sorted(k for k in recorded.keys() | asked.keys() if recorded.get(k) != asked.get(k))
    if differ:
        said = ", ".join(f"{k} {recorded.get(k)!r} there, {asked.get(k)!r} now" for k in differ)
        raise CheckpointError(f"{path}: trained with other settings ({said}); use another --out")


def _seed_json(result: SeedResult, config: OfflineConfig, settings: FlSettings) -> dict:
    return {
        "setting": config.setting.digest(),
        "rounds": config.rounds,
        "settings": settings.training_key(),
        **result.to_json(),
    }


def _load_seed_result(settings: FlSettings, config: OfflineConfig) -> SeedResult:
    path = _seed_file(settings)
    try:
        raw = json.loads(path.read_text())
        if (raw["setting"], raw["rounds"]) != (config.setting.digest(), config.rounds):
            raise CheckpointError(
                f"{path}: a run of another setting or {raw['rounds']} rounds, not "
                f"{config.setting.name} with {config.rounds}; use another --out"
            )
        if "settings" in raw:
            _refuse_other(path, raw["settings"], settings.training_key())
        return SeedResult.from_json(raw)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        if isinstance(exc, CheckpointError):
            raise
        raise CheckpointError(f"{path}: corrupt result; remove it or drop --resume") from None


def _gather(config: OfflineConfig, scenario: Scenario, results: OfflineResults) -> OfflineResults:
    """With ``--resume``: every finished method of ``config.seeds`` in ``out``, also those
    another invocation (e.g. the ablation, or a parallel one on other seeds) wrote."""
    methods = dict(results.methods)
    for seed in config.seeds:
        for path in sorted(config.seed_dir(seed).glob("*/result.json")):
            method = path.parent.name
            if method not in METHODS:
                continue
            settings = config.settings(method, seed, scenario)
            if _finished(settings) is None:
                continue
            block = methods.get(method) or _block(results, settings)
            methods[method] = block.with_seed(_load_seed_result(settings, config))
    return replace(results, methods=methods)


def _fig5_path(config: OfflineConfig, scenario: Scenario) -> Path:
    return config.out / f"fig5_{scenario.name}.png"


def _seeds(seeds: tuple[int, ...]) -> str:
    return " ".join(str(s) for s in seeds)


def record(config: OfflineConfig, scenario: Scenario, seed: int) -> Path:
    """Record (or, resuming, reuse) the crop-field run of ``seed``; returns its folder."""
    run_dir = config.seed_dir(seed) / "data"
    if config.resume and (run_dir / "ground_truth.npz").is_file():
        _same_recording(run_dir / "summary.json", scenario.name, seed, config.duration)
    else:
        simulate(
            scenario,
            environment="crop_field",
            duration=config.duration,
            seed=seed,
            out=run_dir,
            progress=config.progress,
            plot=False,
        )
    load_run(run_dir)  # a corrupt recording fails here, naming the file, before any training
    return run_dir


def _same_recording(path: Path, scenario: str, seed: int, duration: float) -> None:
    """Refuse to train on a kept recording of another scenario, seed or duration."""
    try:
        summary = json.loads(path.read_text())
        ran = (summary["scenario"], summary["seed"], float(summary["sim_seconds"]))
    except (OSError, ValueError, KeyError, TypeError):
        raise CheckpointError(f"{path}: missing or corrupt; remove its folder") from None
    if ran != (scenario, seed, duration):
        raise CheckpointError(
            f"{path}: a recording of {ran[0]} seed {ran[1]}, {ran[2]:g} s, not {scenario} "
            f"seed {seed}, {duration:g} s; use another --out"
        )


def train_method(settings: FlSettings, advance: Callable[[int], None]) -> list[RoundRecord]:
    """Train ``settings.method`` as its ``training`` kind says (resuming a checkpoint when
    ``settings.resume``); returns the round history."""
    done = _finished(settings)
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
    trainer = TRAINERS[settings.method_spec.training]
    return trainer(settings, lambda _: advance(1))


def _finished(settings: FlSettings) -> list[RoundRecord] | None:
    """The history of a resumed method that already finished all its rounds."""
    if not (settings.resume and settings.checkpoint_path.is_file()):
        return None
    checkpoint = load_checkpoint(
        settings.checkpoint_path,
        settings.history_path,
        settings.method,
        like=_start_state(settings),
    )
    return checkpoint.history if checkpoint.server_round >= settings.rounds else None


def _start_state(settings: FlSettings) -> dict[str, torch.Tensor]:
    """The weights a run of ``settings`` starts from, as its checkpoint holds them: the seeded
    initial global model, or for ``local`` training one copy per drone of the run (keys
    ``drone_<id>.<parameter>``)."""
    state = initial_state(settings)
    if settings.method_spec.training != "local":
        return state
    logs = Path(settings.run_dir).glob("drone_*.npz")
    ids = sorted(int(p.stem.removeprefix("drone_")) for p in logs)
    return {f"drone_{d}.{k}": v for d in ids for k, v in state.items()}


def drone_splits(settings: FlSettings) -> dict[int, tuple[WindowSet, WindowSet]]:
    """Every drone's chronological train/test windows, labelled by ground truth."""
    logs, truth = load_run(settings.run_dir)
    spec = settings.windows
    return {
        d: split_windows(log, ground_truth_labels(log, truth), spec)
        for d, log in sorted(logs.items())
    }


def _resume_point(
    settings: FlSettings, state: dict[str, torch.Tensor]
) -> tuple[dict[str, torch.Tensor], int, list[RoundRecord]]:
    """The state, last finished round and history to continue from (the fresh ``state``,
    round 0 and no history unless resuming a checkpoint)."""
    if settings.resume and settings.checkpoint_path.is_file():
        checkpoint = load_checkpoint(
            settings.checkpoint_path, settings.history_path, settings.method, like=state
        )
        return checkpoint.state, checkpoint.server_round, checkpoint.history
    return state, 0, []


def run_centralized(settings: FlSettings, on_round: OnRound | None = None) -> list[RoundRecord]:
    """Pooled training in the cloud: the method's model (``large`` for ``centralized``,
    DroneFL's own for ``centralized-small``) trained on every drone's pooled training windows,
    E epochs per round, evaluated per drone on its test windows (when the run has them)."""
    torch.set_num_threads(1)
    splits = drone_splits(settings)
    pooled = WindowSet.concat([train for train, _ in splits.values()])
    model = build_model(settings.model, seed=settings.seed)
    state, offset, history = _resume_point(settings, initial_state(settings))
    model.load_state_dict(state)
    for server_round in range(offset + 1, settings.rounds + 1):
        stats = train_local(model, pooled, settings.train_config(server_round, 0))
        test = {}
        if settings.evaluates:
            test = {d: evaluate(model, test_set) for d, (_, test_set) in splits.items()}
        crash_point(f"round-end:{server_round}")
        entry = RoundRecord(server_round, test, {0: stats.loss})
        history.append(entry)
        save_checkpoint(
            settings.checkpoint_path,
            settings.history_path,
            Checkpoint(settings.method, server_round, model.state_dict(), history),
        )
        if on_round is not None:
            on_round(entry)
    return history


def run_local(settings: FlSettings, on_round: OnRound | None = None) -> list[RoundRecord]:
    """Each drone alone: its own model (same seeded initialisation as FL), trained E epochs
    per round on its own training windows with the same per-(round, drone) seeds as the
    FL clients, never aggregated, evaluated on its own test windows. The checkpoint holds
    every drone's model (keys ``drone_<id>.<parameter>``)."""
    torch.set_num_threads(1)
    splits = drone_splits(settings)
    state, offset, history = _resume_point(settings, _start_state(settings))
    models = {}
    for d in splits:
        models[d] = build_model(settings.model, seed=settings.seed)
        prefix = f"drone_{d}."
        models[d].load_state_dict(
            {k[len(prefix) :]: v for k, v in state.items() if k.startswith(prefix)}
        )
    for server_round in range(offset + 1, settings.rounds + 1):
        losses, test = {}, {}
        for d, (train_set, test_set) in splits.items():
            stats = train_local(models[d], train_set, settings.train_config(server_round, d))
            losses[d] = stats.loss
            if settings.evaluates:
                test[d] = evaluate(models[d], test_set)
        entry = RoundRecord(server_round, test, losses)
        history.append(entry)
        state = {f"drone_{d}.{k}": v for d, m in models.items() for k, v in m.state_dict().items()}
        save_checkpoint(
            settings.checkpoint_path,
            settings.history_path,
            Checkpoint(settings.method, server_round, state, history),
        )
        if on_round is not None:
            on_round(entry)
    return history


#: How each ``training`` kind of :mod:`dronefl.fl.methods` runs.
TRAINERS: dict[str, Callable[[FlSettings, OnRound | None], list[RoundRecord]]] = {
    "federated": run_federated,
    "pooled": run_centralized,
    "local": run_local,
}


def reduction(dronefl: float, baseline: float) -> float:
    """DroneFL's MSE reduction against a baseline, % (positive = DroneFL better)."""
    return 100.0 * (baseline - dronefl) / baseline if baseline > 0 else math.nan


def comparison_table(all_results: list[OfflineResults], methods: tuple[str, ...]) -> str:
    """Markdown: final test MSE (mean +- std over seeds) of ``methods`` per scenario, the
    per-drone means, and DroneFL's % reduction against each other method."""
    methods = tuple(m for m in methods if any(m in r.methods for r in all_results))
    lines = [
        "Final average test MSE (m^2) after the last round, mean +- std over seeds; lower is "
        "better.",
        "",
        "| scenario | seeds | " + " | ".join(methods) + " |",
        "|---|---|" + "---|" * len(methods),
    ]
    for r in all_results:
        seeds = sorted({s.seed for b in r.methods.values() for s in b.seeds})
        cells = [_fmt(r.methods.get(m)) for m in methods]
        lines.append(f"| {r.scenario} | {_seeds(tuple(seeds))} | " + " | ".join(cells) + " |")
    lines += ["", "Per drone, mean over seeds (m^2):", ""]
    lines += ["| scenario | method | " + "per drone |", "|---|---|---|"]
    for r in all_results:
        for m in methods:
            if m in r.methods:
                per = r.methods[m].final_test_mse_per_drone
                cells = " / ".join(f"{v:.3g}" for v in per.values())
                lines.append(f"| {r.scenario} | {m} | {cells} |")
    others = [m for m in methods if m != "dronefl"]
    lines += ["", "DroneFL's MSE reduction against each method, % (of the seed means):", ""]
    lines += ["| scenario | " + " | ".join(others) + " |", "|---|" + "---|" * len(others)]
    for r in all_results:
        mine = r.methods.get("dronefl")
        cells = []
        for m in others:
            base = r.methods.get(m)
            ok = mine is not None and base is not None
            cells.append(
                f"{reduction(mine.final_test_mse, base.final_test_mse):+.1f}" if ok else ""
            )
        lines.append(f"| {r.scenario} | " + " | ".join(cells) + " |")
    for r in all_results:
        mine, alone = r.methods.get("dronefl"), r.methods.get("local")
        if mine is None or alone is None:
            continue
        if len({s.seed for s in mine.seeds} & {s.seed for s in alone.seeds}) < 2:
            continue
        lines += ["", f"{r.scenario}: DroneFL against `local` per drone, paired over the seeds "
                  "(`dronefl fl-compare`):", ""]  # fmt: skip
        lines.append(paired_markdown(paired_comparison(mine, alone), "dronefl", "local"))
    return "\n".join(lines) + "\n"


def _fmt(block: MethodResult | None) -> str:
    if block is None:
        return ""
    return f"{block.final_test_mse:.3g} ± {block.final_test_mse_std:.2g}"


def run_ablation(
    out: Path,
    scenarios: tuple[str, ...] = PAPER_CASES,
    rounds: int = 50,
    seeds: tuple[int, ...] = EVALUATION_SEEDS,
    stride: int = 10,
    setting: Setting | None = None,
    resume: bool = False,
    progress: bool = True,
) -> list[OfflineResults]:
    """DroneFL, DroneFL without AdaIN and without relative positions, on each scenario.

    Writes ``out/<scenario>/`` per scenario, ``out/ablation_<scenario>.png`` and
    ``out/ablation.md``. With ``resume`` and the ``out`` of an earlier ``fl-offline`` run per
    scenario (``out/<scenario>``), its recordings and finished ``dronefl`` runs are reused and
    the ablation's results are added to its ``results.json``.
    """
    all_results = []
    for name in scenarios:
        scenario = load_scenario(name)
        config = OfflineConfig(
            name,
            out / scenario.name,
            setting or Setting.load(),
            rounds,
            seeds,
            stride=stride,
            methods=ABLATION_METHODS,
            resume=resume,
            progress=progress,
        )
        results = run_fl_offline(config, scenario)
        curves = {m: results.methods[m].curve for m in ABLATION_METHODS}
        plot_fig5(curves, f"{scenario.name} ablation", out / f"ablation_{scenario.name}.png")
        all_results.append(results)
    atomic_write_text(out / "ablation.md", comparison_table(all_results, ABLATION_METHODS))
    return all_results


def altitude_scenario(base: Scenario, altitude_2: float) -> Scenario:
    """Fig. 4's set-up from a two-drone ``base`` scenario (each drone over its own vehicle,
    so different horizontal positions): drone 2 flies at ``altitude_2`` m."""
    if len(base.drones) != 2:
        raise ValueError(
            f"--scenario: the altitude study needs a two-drone scenario, {base.name} has "
            f"{len(base.drones)}"
        )
    raw = scenario_dict(base)
    raw["name"] = f"{base.name}-altitude-{altitude_2:g}m"
    raw["description"] = "Fig. 4 motivation study"
    raw["drones"][1]["altitude"] = altitude_2
    return parse_scenario(raw, source=raw["name"])


def run_altitude_study(
    out: Path,
    scenario: str = "case1",
    rounds: int = 50,
    seeds: tuple[int, ...] = EVALUATION_SEEDS,
    stride: int = 10,
    methods: tuple[str, ...] = ("dronefl-no-adain", "dronefl"),
    setting: Setting | None = None,
    resume: bool = False,
    progress: bool = True,
) -> dict:
    """Drone 1's test MSE per round (mean over seeds) when drone 2 flies at (almost) drone 1's
    altitude (0.1 m lower: scenarios need distinct altitudes) or 10 m lower. Writes
    ``out/altitude.json`` and ``out/fig4_altitude.png``."""
    base = load_scenario(scenario)
    altitude_1 = base.drones[0].altitude
    study: dict = {"scenario": base.name, "rounds": rounds, "seeds": list(seeds), "drone": 1}
    study["curves"] = {}
    curves = {}
    for label, altitude in (("same altitude", altitude_1 - 0.1), ("different", altitude_1 - 10)):
        config = OfflineConfig(
            scenario,
            out / label.replace(" ", "_"),
            setting or Setting.load(),
            rounds,
            seeds,
            stride=stride,
            methods=methods,
            resume=resume,
            progress=progress,
        )
        results = run_fl_offline(config, altitude_scenario(base, altitude))
        for method in methods:
            first = base.drones[0].id
            per_seed = np.array(
                [_history_of_drone(config, method, s, first, base) for s in seeds]
            )  # (S, R)
            name = f"{method}, {label} (drone 2 at {altitude:g} m)"
            curves[name] = Curve(tuple(per_seed.mean(axis=0)), tuple(per_seed.std(axis=0)))
            study["curves"][name] = {
                "altitude_drone_2": altitude,
                "drone_1_test_mse": list(curves[name].mean),
                "drone_1_test_mse_std": list(curves[name].std),
                "final": results.methods[method].final_test_mse_per_drone[first],
                "final_std": results.methods[method].final_test_mse_per_drone_std[first],
            }
    atomic_write_json(out / "altitude.json", study)
    plot_altitude(curves, out / "fig4_altitude.png")
    return study


def _history_of_drone(
    config: OfflineConfig, method: str, seed: int, drone: int, scenario: Scenario
) -> list[float]:
    settings = config.settings(method, seed, scenario)
    history = load_checkpoint(settings.checkpoint_path, settings.history_path, method).history
    return [r.test_mse[drone] for r in history]
