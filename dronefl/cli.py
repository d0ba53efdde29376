"""The ``dronefl`` command. Every sub-command validates its inputs before doing any work and
exits with code 2 and one line naming the bad file/field on bad input."""

from __future__ import annotations

import os
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, NoReturn

import typer

from dronefl.bench.command import bench as bench_command
from dronefl.config import (
    ENVIRONMENTS,
    Scenario,
    ScenarioError,
    builtin_scenarios,
    load_scenario,
)
from dronefl.fl import TrainingError
from dronefl.logs import LogError
from dronefl.perception import DETECTORS
from dronefl.validation import check_duration, check_one_of, check_seeds

if TYPE_CHECKING:
    from dronefl.experiments.track import TrackConfig
    from dronefl.settings import Setting

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="DroneFL: federated learning for multi-drone visual target tracking.",
)

#: How long the process waits at exit for threads that are still running, s.
EXIT_GRACE_S = 5.0
#: Exit code after Ctrl-C (SIGINT), as Click gives it: 128 + 2.
INTERRUPTED = 130
#: Exit code after SIGTERM: 128 + 15.
TERMINATED_CODE = 128 + signal.SIGTERM
#: Set once SIGTERM has arrived.
TERMINATED = threading.Event()

#: Errors that mean "bad input": reported as one line, exit code 2, no traceback.
USER_ERRORS: tuple[type[Exception], ...] = (ScenarioError, LogError, FileNotFoundError)


def fail(message: str) -> typer.Exit:
    """Print ``message`` as a one-line error and return the exit to raise (code 2)."""
    typer.secho(f"error: {message}", err=True, fg="red")
    return typer.Exit(code=2)


ScenarioOption = Annotated[
    str,
    typer.Option("--scenario", "-s", help="Built-in scenario (case1|case2|case3) or YAML path."),
]
EnvOption = Annotated[
    str | None,
    typer.Option("--env", help=f"Environment: {'|'.join(ENVIRONMENTS)} (default: the scenario's)."),
]
SeedOption = Annotated[int, typer.Option("--seed", min=0, help="Random seed of the run.")]


def writable_folder(out: Path) -> Path:
    """Reject an ``--out`` that cannot become a writable folder, before any work: its nearest
    existing ancestor must be a folder in which a file can be created."""
    existing = out
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise typer.BadParameter(f"{out}: {existing} is not a folder", param_hint="--out")
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as exc:
        raise typer.BadParameter(
            f"{out}: cannot write in {existing} ({exc.strerror})", param_hint="--out"
        ) from None
    return out


OutOption = Annotated[
    Path, typer.Option("--out", "-o", help="Run folder to write.", callback=writable_folder)
]


SettingOption = Annotated[
    str,
    typer.Option(
        "--setting", help="recommended | paper | a TOML file (see `dronefl setting show`)."
    ),
]
SetOption = Annotated[
    list[str] | None,
    typer.Option("--set", help="One setting field, section.field=value (repeatable)."),
]


def _setting(name: str, overrides: list[str] | None) -> Setting:
    """The setting ``name`` (or file) with ``overrides``; one line and exit 2 when bad."""
    from dronefl.settings import Setting, SettingError

    try:
        return Setting.load(name, overrides or ())
    except SettingError as exc:
        raise fail(str(exc)) from None


def check_choice(value: str | None, choices: tuple[str, ...], option: str) -> None:
    """Reject ``value`` (exit 2, one line) unless it is one of ``choices`` (None passes)."""
    if value is None:
        return
    try:
        check_one_of(value, choices, option)
    except ValueError as exc:
        raise fail(str(exc)) from None


@app.command()
def simulate(
    scenario: ScenarioOption = "case1",
    env: EnvOption = None,
    duration: Annotated[float, typer.Option(help="Simulated seconds.")] = 600.0,
    seed: SeedOption = 0,
    out: OutOption = Path("runs/simulate"),
    detector: Annotated[str, typer.Option(help="projection|yolo")] = "projection",
) -> None:
    """Record a run under the scripted pilot: onboard logs, ground truth, summary, top-down PNG.

    Example: dronefl simulate --scenario case3 --env orchard --duration 600 --seed 0 --out runs/c3
    """
    from dronefl.experiments.simulate import format_summary
    from dronefl.experiments.simulate import simulate as run

    check_choice(env, ENVIRONMENTS, "--env")
    check_choice(detector, DETECTORS, "--detector")
    spec = load_scenario(scenario)
    try:
        check_duration(duration, spec.dt)
        check_seeds([seed])
    except ValueError as exc:
        raise fail(str(exc)) from None
    summary = run(spec, environment=env, duration=duration, seed=seed, out=out, detector=detector)
    typer.echo(format_summary(summary))
    typer.echo(f"wrote {out}/ (drone_<id>.npz, ground_truth.npz, summary.json, topdown.png)")


@app.command()
def scenarios(
    name: Annotated[str | None, typer.Argument(help="Scenario to validate and show.")] = None,
) -> None:
    """List the built-in scenarios, or validate one (name or YAML path) and print it.

    Example: dronefl scenarios case2        dronefl scenarios my_farm.yaml
    """
    if name is None:
        for builtin in builtin_scenarios():
            spec = load_scenario(builtin)
            typer.echo(f"{builtin:8s} {spec.description}")
        return
    spec = load_scenario(name)
    typer.echo(f"{spec.name}: {spec.description} (valid)")
    typer.echo(
        f"  field {spec.field.width} x {spec.field.height} m, {spec.field.n_lanes} lanes, "
        f"{spec.environment}, {spec.rate_hz} Hz"
    )
    for t in spec.targets:
        typer.echo(f"  target {t.id}: lane {t.lane}, {t.motion} {t.speed} m/s")
    for d in spec.drones:
        typer.echo(f"  drone {d.id}: {d.altitude} m, watches {list(d.targets)}")


@app.command()
def demo(
    out: OutOption = Path("runs/demo"),
    scenario: ScenarioOption = "case2",
    duration: Annotated[float, typer.Option(help="Simulated seconds per episode.")] = 600.0,
) -> None:
    """The default experiment: closed-loop tracking of Case 2 in the orchard, DroneFL (an FL
    round every 100 s) beside fixed distributed models, both pretrained in the crop field, in
    the recommended setting, for 600 s: seed 0 of the README's Table I row of that setting.

    Example: dronefl demo --out runs/demo
    """
    from dronefl.experiments.track import run_episode
    from dronefl.report.tables import comparison

    spec = load_scenario(scenario)
    setting = _setting("recommended", [])
    results = []
    for method in ("fixed", "dronefl"):
        config = _track_config(
            scenario=spec, setting=setting, method=method, seed=0, duration=duration,
            out=out / method, pretrained=out / "pretrained",
        )  # fmt: skip
        results.append(run_episode(config))
    typer.echo(comparison(results))
    typer.echo(
        f"setting: recommended (digest {setting.digest()}; `dronefl setting show recommended` "
        "prints it; docs/closed_loop.md)"
    )
    typer.echo(
        f"wrote {out}/<method>/ (metrics.json, trajectories.png, timeseries.png, episode.gif)"
    )


RoundsOption = Annotated[int, typer.Option("--rounds", help="Global FL rounds.")]
StrideOption = Annotated[int, typer.Option("--stride", help="Samples between training windows.")]
ResumeOption = Annotated[
    bool, typer.Option("--resume", help="Continue finished work and checkpoints in --out.")
]


def _fl_errors() -> tuple[type[Exception], ...]:
    from dronefl.fl.checkpoint import CheckpointError
    from dronefl.fl.records import SettingsError

    return (SettingsError, CheckpointError, ValueError)


SeedsOption = Annotated[
    str, typer.Option("--seeds", help='Seeds, e.g. "0 1 2 3 4" (recording, model, training).')
]
FlScenarioOption = Annotated[
    str | None,
    typer.Option("--scenario", "-s", help="Built-in scenario (case1|case2|case3) or YAML path."),
]


def _parse_seeds(text: str) -> tuple[int, ...]:
    """``"0 1 2"`` or ``"0,1,2"`` -> ``(0, 1, 2)``, each in [0, 2^32)."""
    try:
        seeds = tuple(int(s) for s in text.replace(",", " ").split())
    except ValueError:
        raise fail(f"--seeds: {text!r} is not a list of integers") from None
    if not seeds:
        raise fail("--seeds: give at least one seed")
    try:
        check_seeds(seeds, "--seeds")
    except ValueError as exc:
        raise fail(str(exc)) from None
    return seeds


def _scenario_name(scenario: str | None, default: str) -> str:
    name = scenario or default
    load_scenario(name)  # a bad name or file fails here, before any work
    return name


def _summary_line(method: str, block) -> str:
    per = " / ".join(f"{v:.3g}" for v in block.final_test_mse_per_drone.values())
    return (
        f"{method:18s} final test MSE {block.final_test_mse:.4g} ± {block.final_test_mse_std:.2g}"
        f" m^2 (per drone {per}; {len(block.seeds)} seeds)"
    )


@app.command("fl-offline")
def fl_offline(
    scenario: FlScenarioOption = None,
    rounds: RoundsOption = 50,
    seeds: SeedsOption = "0 1 2 3 4",
    out: OutOption = Path("runs/fl_offline"),
    methods: Annotated[
        str, typer.Option(help="Comma-separated methods (see dronefl.fl.methods).")
    ] = "fedavg,fedprox,fedper,dronefl,centralized,centralized-small,local",
    duration: Annotated[float, typer.Option(help="Simulated seconds recorded.")] = 600.0,
    stride: StrideOption = 10,
    setting: SettingOption = "recommended",
    set_: SetOption = None,
    resume: ResumeOption = False,
    faults: Annotated[
        str, typer.Option(help="Injected drone faults ROUND:DRONE:KIND,... (dronefl.fl.faults).")
    ] = "",
) -> None:
    """Offline FL (paper Fig. 5): record the scenario per seed, train every method as the
    setting's [model] and [training] say, plot and tabulate (mean +- std over seeds).

    Example: dronefl fl-offline --scenario case2 --rounds 50 --seeds "0 1 2" --out runs/fl/case2
    """
    from dronefl.experiments.fl_offline import OfflineConfig, run_fl_offline
    from dronefl.models.model import parameter_summary

    name = _scenario_name(scenario, "case1")
    try:
        config = OfflineConfig(
            name, out, _setting(setting, set_), rounds, _parse_seeds(seeds), duration, stride,
            tuple(methods.split(",")), resume, faults=faults,
        )  # fmt: skip
        typer.echo(parameter_summary())
        results = run_fl_offline(config)
    except _fl_errors() as exc:
        raise fail(str(exc)) from None
    for method, block in results.methods.items():
        typer.echo(_summary_line(method, block))
    typer.echo(f"wrote {out}/ (results.json, fig5_{results.scenario}.png, table.md)")


@app.command("fl-compare")
def fl_compare(
    results: Annotated[Path, typer.Argument(help="An fl-offline results.json.")],
    method_a: Annotated[str, typer.Argument(help="Method A, read from RESULTS.")],
    method_b: Annotated[str, typer.Argument(help="Method B, read from RESULTS or --against.")],
    against: Annotated[
        Path | None, typer.Option(help="Another results.json to read method B from.")
    ] = None,
) -> None:
    """Paired per-seed comparison of two methods' final test MSE, per drone: the mean
    difference A - B with its standard error, the seeds on which A is lower, and the paired
    t-test's p (dronefl.report.paired).

    Example: dronefl fl-compare runs/fl_step/case3/results.json dronefl local
    """
    from dronefl.fl.checkpoint import CheckpointError
    from dronefl.report.paired import paired_comparison, paired_markdown
    from dronefl.results.fl import OfflineResults

    try:
        first = OfflineResults.load(results)
        second = OfflineResults.load(against) if against is not None else first
        wanted = ((method_a, first, results), (method_b, second, against or results))
        for method, source, file in wanted:
            if method not in source.methods:
                raise ValueError(f"{file}: no method {method!r} (it has {sorted(source.methods)})")
        rows = paired_comparison(first.methods[method_a], second.methods[method_b])
    except (CheckpointError, ValueError) as exc:
        raise fail(str(exc)) from None
    label_b = method_b if against is None else f"{method_b} ({against.parent.name})"
    seeds = " ".join(map(str, rows[0].seeds))
    typer.echo(f"{first.scenario}, final test MSE per drone, seeds {seeds}")
    typer.echo(paired_markdown(rows, method_a, label_b))


#: Units of Table I's columns, for ``table1-compare``.
TABLE1_UNITS = {
    "prediction_error": "m²", "tracking_distance": "m²", "uncertainty": "m²",
    "speed_change": "m/s", "total_cost": "J", "sent_prediction_error": "m²",
    "tracking_error": "m²", "ospa": "m", "gospa": "m",
}  # fmt: skip


@app.command("table1-compare")
def table1_compare(
    table: Annotated[Path, typer.Argument(help="A table1 run's table1.csv.")],
    method_a: Annotated[str, typer.Argument(help="Method A, e.g. dronefl.")],
    method_b: Annotated[str, typer.Argument(help="Method B, e.g. fixed.")],
    metrics: Annotated[
        str, typer.Option(help="Space-separated table1.csv columns to compare.")
    ] = "prediction_error tracking_distance",
) -> None:
    """Paired per-seed comparison of two closed-loop methods of Table I, per scenario and
    metric: the mean difference A - B with its standard error, the seeds on which A is lower,
    and the paired t-test's p (dronefl.report.paired).

    Example: dronefl table1-compare runs/table1/table1.csv dronefl fixed
    """
    from dronefl.report.paired import paired_markdown, table1_comparison

    try:
        tables = [(m, table1_comparison(table, method_a, method_b, m)) for m in metrics.split()]
    except (OSError, ValueError) as exc:
        raise fail(str(exc)) from None
    for metric, rows in tables:
        typer.echo(f"{metric}, seeds {' '.join(map(str, rows[0].seeds))}:")
        typer.echo(
            paired_markdown(rows, method_a, method_b, "scenario", TABLE1_UNITS.get(metric, ""))
        )


@app.command("fl-ablation")
def fl_ablation(
    scenario: Annotated[
        str, typer.Option("--scenario", "-s", help="Comma-separated scenarios (names or YAML).")
    ] = "case1,case2,case3",
    rounds: RoundsOption = 50,
    seeds: SeedsOption = "0 1 2 3 4",
    out: OutOption = Path("runs/fl_ablation"),
    stride: StrideOption = 10,
    setting: SettingOption = "recommended",
    set_: SetOption = None,
    resume: ResumeOption = False,
) -> None:
    """DroneFL without AdaIN and without relative positions, on each scenario.

    Example: dronefl fl-ablation --rounds 50 --out runs/fl   (reuses runs/fl/<scenario> with
    --resume)
    """
    from dronefl.experiments.fl_offline import run_ablation

    names = tuple(_scenario_name(n, n) for n in scenario.split(","))
    try:
        chosen = _setting(setting, set_)
        run_ablation(out, names, rounds, _parse_seeds(seeds), stride, chosen, resume)
    except _fl_errors() as exc:
        raise fail(str(exc)) from None
    typer.echo((out / "ablation.md").read_text())


@app.command("image-baseline")
def image_baseline(
    scenario: ScenarioOption = "case1",
    duration: Annotated[float, typer.Option(help="Seconds recorded in each environment.")] = 600.0,
    epochs: Annotated[int, typer.Option(help="Training epochs of both models.")] = 30,
    seed: SeedOption = 0,
    frame_px: Annotated[int, typer.Option(help="Frame size the image model reads, px.")] = 48,
    out: OutOption = Path("runs/image_baseline"),
) -> None:
    """The paper's centralized baseline, offline: an image model (frames + odometry, end to
    end) and the box-based large model, both trained on the crop field's first 80 % and scored
    on its last 20 % and on an orchard run (SPEC §8). Renders every frame once (cached).

    Example: dronefl image-baseline --scenario case1 --out runs/image_baseline
    """
    from dronefl.experiments.image_baseline import ImageBaselineConfig, run_image_baseline

    try:
        config = ImageBaselineConfig(
            load_scenario(scenario), out, duration, epochs, seed=seed, frame_px=frame_px
        )
    except ValueError as exc:
        raise fail(str(exc)) from None
    results = run_image_baseline(config)
    typer.echo(f"{scenario}: mean squared distance (m²) of the prediction, per drone")
    for model, scores in results["mse"].items():
        for where, per_drone in scores.items():
            values = "  ".join(f"drone {d}: {v:7.3f}" for d, v in per_drone.items())
            typer.echo(f"  {model:6s} {where:20s} {values}")
    image = results["image_model"]
    typer.echo(
        f"image model: {image['parameters']} parameters, {image['train_seconds_per_epoch']:.1f}"
        f" s per epoch ({image['training_windows']} windows), "
        f"{image['inference_ms_per_sample']:.2f} ms per sample; box model: "
        f"{results['box_model']['parameters']} parameters"
    )
    typer.echo(f"wrote {out}/results.json")


@app.command("fl-altitude")
def fl_altitude(
    scenario: FlScenarioOption = None,
    rounds: RoundsOption = 50,
    seeds: SeedsOption = "0 1 2 3 4",
    out: OutOption = Path("runs/fl_altitude"),
    methods: Annotated[
        str, typer.Option(help="Comma-separated methods.")
    ] = "dronefl-no-adain,dronefl",
    stride: StrideOption = 10,
    setting: SettingOption = "recommended",
    set_: SetOption = None,
    resume: ResumeOption = False,
) -> None:
    """Altitude motivation study (paper Fig. 4): drone 1's test MSE per round with drone 2 at
    the same or a 10 m lower altitude (a two-drone scenario, default case1).

    Example: dronefl fl-altitude --rounds 50 --seeds "0 1 2" --out runs/fl_altitude
    """
    from dronefl.experiments.fl_offline import run_altitude_study

    name = _scenario_name(scenario, "case1")
    try:
        study = run_altitude_study(
            out,
            name,
            rounds,
            _parse_seeds(seeds),
            stride,
            tuple(methods.split(",")),
            _setting(setting, set_),
            resume,
        )
    except _fl_errors() as exc:
        raise fail(str(exc)) from None
    for label, curve in study["curves"].items():
        typer.echo(
            f"{label:52s} drone 1 final test MSE {curve['final']:.4g} ± {curve['final_std']:.2g}"
            " m^2"
        )
    typer.echo(f"wrote {out}/ (altitude.json, fig4_altitude.png)")


detector_app = typer.Typer(
    no_args_is_help=True, help="The vision path: render a dataset, train, evaluate, draw figures."
)
app.add_typer(detector_app, name="detector")
DatasetDirOption = Annotated[
    Path, typer.Option("--data", help="Dataset folder (from `dronefl detector dataset`).")
]
WeightsOption = Annotated[
    Path | None, typer.Option("--weights", help="ONNX detector (default: the shipped one).")
]


@detector_app.command("dataset")
def detector_dataset(
    out: OutOption = Path("runs/detector/dataset"),
    train_per_env: Annotated[int, typer.Option(help="Training frames per environment.")] = 800,
    val_per_env: Annotated[int, typer.Option(help="Validation frames per environment.")] = 80,
    test_per_env: Annotated[int, typer.Option(help="Held-out frames per environment.")] = 150,
    seed: SeedOption = 0,
) -> None:
    """Render frames of crop_field and orchard with exact YOLO labels, split train/val/test.

    Example: dronefl detector dataset --out runs/detector/dataset
    """
    from rich.progress import track

    from dronefl.perception.dataset import DatasetConfig, write_dataset

    try:
        config = DatasetConfig(train_per_env, val_per_env, test_per_env, seed=seed)
    except ValueError as exc:
        raise fail(str(exc)) from None
    counts = write_dataset(out, config, progress=lambda jobs: track(jobs, "rendering"))
    typer.echo(f"wrote {out}/ {counts} (data.yaml, data_<environment>.yaml)")


@detector_app.command("train")
def detector_train(
    data: DatasetDirOption = Path("runs/detector/dataset"),
    out: OutOption = Path("runs/detector/run"),
    imgsz: Annotated[int, typer.Option(help="Network input size, px.")] = 320,
    epochs: Annotated[int, typer.Option(help="Training epochs.")] = 22,
    threads: Annotated[int, typer.Option(help="torch CPU threads.")] = 2,
    ship: Annotated[bool, typer.Option(help="Copy the ONNX into dronefl/assets/.")] = True,
) -> None:
    """Train YOLO11n from yolo11n.yaml (no pretrained weights) and export ONNX.

    Example: nice -n 10 dronefl detector train --data runs/detector/dataset --epochs 22
    """
    from dronefl.perception.training import (
        TrainConfig,
        detector_sidecar,
        ship_detector,
        train_detector,
    )

    try:
        config = TrainConfig(imgsz=imgsz, epochs=epochs, threads=threads)
    except ValueError as exc:
        raise fail(str(exc)) from None
    record = train_detector(data / "data.yaml", out, config)
    typer.echo(f"trained in {record.train_seconds / 60:.1f} min; ONNX at {record.onnx}")
    if ship:
        command = f"dronefl detector train --data {data} --imgsz {imgsz} --epochs {epochs}"
        shipped = ship_detector(record.onnx, detector_sidecar(data, record, command))
        typer.echo(f"shipped {shipped}")


@detector_app.command("evaluate")
def detector_evaluate(
    data: DatasetDirOption = Path("runs/detector/dataset"),
    weights: WeightsOption = None,
    out: OutOption = Path("runs/detector/eval"),
    ship_noise: Annotated[
        bool, typer.Option(help="Write the fitted projection noise into dronefl/assets/.")
    ] = True,
) -> None:
    """mAP per environment, box error and miss rate vs altitude; fit the projection noise.

    Example: dronefl detector evaluate --data runs/detector/dataset --out runs/detector/eval
    """
    from dronefl.perception.evaluation import evaluate_detector, format_report, ship_evaluation
    from dronefl.perception.yolo import shipped_detector_path

    try:
        report = evaluate_detector(weights or shipped_detector_path(), data, out)
    except ValueError as exc:  # corrupt weights or scene records
        raise fail(str(exc)) from None
    typer.echo(format_report(report))
    if ship_noise:
        for path in ship_evaluation(report, update_sidecar=weights is None):
            typer.echo(f"wrote {path}")


@detector_app.command("figures")
def detector_figures(
    out: OutOption = Path("docs/img"),
    weights: WeightsOption = None,
    eval_json: Annotated[
        Path, typer.Option("--eval", help="eval.json of `dronefl detector evaluate`.")
    ] = Path("runs/detector/eval/eval.json"),
) -> None:
    """README figures: Case 3 frames of both environments with detections, quality vs altitude.

    Example: dronefl detector figures --out docs/img
    """
    from dronefl.report.frames import write_detector_figures

    if not eval_json.is_file():
        raise fail(f"--eval: no {eval_json}: run `dronefl detector evaluate` first")
    try:
        written = write_detector_figures(out, weights, eval_json)
    except ValueError as exc:  # corrupt weights
        raise fail(str(exc)) from None
    for path in written:
        typer.echo(f"wrote {path}")


TrackMethod = Annotated[
    str,
    typer.Option(
        "--method", help="dronefl|fixed|centralized|centralized-image (needs --detector yolo)."
    ),
]
PretrainedOption = Annotated[
    Path, typer.Option(help="Cache of pretrained models.", callback=writable_folder)
]


def _track_config(**kwargs: object) -> TrackConfig:
    from dronefl.experiments.track import TrackConfig

    try:
        return TrackConfig(**kwargs)
    except ValueError as exc:
        raise fail(str(exc)) from None


@app.command()
def track(
    scenario: ScenarioOption = "case2",
    method: TrackMethod = "dronefl",
    seed: SeedOption = 0,
    duration: Annotated[float, typer.Option(help="Simulated seconds.")] = 600.0,
    env: Annotated[str, typer.Option("--env", help="Deployment environment.")] = "orchard",
    detector: Annotated[str, typer.Option(help="projection|yolo")] = "projection",
    setting: SettingOption = "recommended",
    set_: SetOption = None,
    pretrained: PretrainedOption = Path("runs/pretrained"),
    out: OutOption = Path("runs/track"),
    animate: Annotated[bool, typer.Option(help="Also write episode.gif.")] = True,
    resume: ResumeOption = False,
) -> None:
    """Closed-loop tracking: detect, predict, fuse, plan every 0.2 s; an FL round every 100 s.

    Writes metrics.json, episode.npz, trajectories.png, timeseries.png and episode.gif, and a
    checkpoint after every FL period (--resume continues a killed episode from it). Every
    knob of the method is in the setting (--setting, --set).
    Example: dronefl track --scenario case2 --setting paper --set learning.period=50 --out runs/c2
    """
    from dronefl.experiments.track import run_episode
    from dronefl.fl.checkpoint import CheckpointError
    from dronefl.report.tables import format_metrics
    from dronefl.serialize import ResultError

    config = _track_config(
        scenario=load_scenario(scenario), setting=_setting(setting, set_), method=method,
        seed=seed, duration=duration, environment=env, detector=detector,
        pretrained=pretrained, out=out, animate=animate, resume=resume,
    )  # fmt: skip
    try:
        metrics = run_episode(config)
    except (CheckpointError, ResultError) as exc:  # a corrupt or foreign file in --out
        raise fail(str(exc)) from None
    typer.echo(format_metrics(metrics))
    typer.echo(f"wrote {out}/ (metrics.json, trajectories.png, timeseries.png, episode.gif)")


def _scenario_list(text: str, option: str) -> tuple[Scenario, ...]:
    """``"case1 case2 my.yaml"`` -> the validated scenarios."""
    names = text.replace(",", " ").split()
    if not names:
        raise fail(f"{option}: give at least one scenario")
    return tuple(load_scenario(n) for n in names)


@app.command()
def table1(
    seeds: Annotated[
        str, typer.Option("--seeds", help="Seeds, e.g. '0 1 2 3 4' or 0,1,2.")
    ] = "0 1 2 3 4",
    scenarios: Annotated[
        str, typer.Option("--scenarios", help="Scenario names or YAML paths, e.g. 'case1 case2'.")
    ] = "case1 case2 case3",
    methods: Annotated[
        str,
        typer.Option(
            "--methods",
            help="Closed-loop methods (default: centralized fixed dronefl; with --detector yolo "
            "centralized-image fixed dronefl, the paper's image baseline on the frames).",
        ),
    ] = "",
    duration: Annotated[float, typer.Option(help="Simulated seconds per episode.")] = 600.0,
    detector: Annotated[
        str, typer.Option(help="projection|yolo (yolo: every drone's frame rendered each step).")
    ] = "projection",
    setting: SettingOption = "recommended",
    set_: SetOption = None,
    pretrained: PretrainedOption = Path("runs/pretrained"),
    label_ablation: Annotated[
        bool,
        typer.Option(
            "--label-ablation",
            help="Also DroneFL with each other source of pseudo-labels (smoothed, filtered, "
            "ground_truth), as rows dronefl[labels=SOURCE].",
        ),
    ] = False,
    out: OutOption = Path("runs/table1"),
) -> None:
    """Table I: every scenario x method x seed; markdown, CSV and a plot.

    Finished episodes (of the same settings, the detector included) are reused, so an
    interrupted run resumes. --label-ablation adds DroneFL's label-ablation rows.
    Example: dronefl table1 --seeds "0 1 2 3 4" --scenarios "case1 case2 case3" --out runs/table1
    """
    from dronefl.experiments.table1 import TABLE1_METHODS, episode_configs, run_table1
    from dronefl.experiments.track import TRACK_METHODS

    check_choice(detector, DETECTORS, "--detector")
    specs = _scenario_list(scenarios, "--scenarios")
    chosen = tuple(methods.replace(",", " ").split()) or TABLE1_METHODS[detector]
    for method in chosen:
        check_choice(method, TRACK_METHODS, "--methods")
    base = _track_config(
        scenario=specs[0], setting=_setting(setting, set_), duration=duration, detector=detector,
        pretrained=pretrained, out=out,
    )  # fmt: skip
    seed_list = _parse_seeds(seeds)
    try:
        episode_configs(base, specs, chosen, seed_list, label_ablation)  # each one checked
    except ValueError as exc:  # a method that cannot fly these settings, a bad seed
        raise fail(str(exc)) from None
    episodes = run_table1(base, specs, chosen, seed_list, label_ablation)
    typer.echo((out / "table1.md").read_text())
    typer.echo(f"wrote {out}/table1.md, table1.csv, table1.png ({len(episodes)} episodes)")


@app.command()
def pretrain(
    scenario: ScenarioOption = "case2",
    setting: SettingOption = "recommended",
    set_: SetOption = None,
    image: Annotated[
        bool,
        typer.Option(
            "--image",
            help="Also the image model of centralized-image (renders the recording: minutes).",
        ),
    ] = False,
    out: OutOption = Path("runs/pretrained"),
) -> None:
    """Prepare the closed loop's models: pretrain them in the crop field (DroneFL by FL, the
    large centralized model on pooled data; with --image the paper's image model on the
    rendered frames) as the setting's [pretraining] says, L_p -> L_f = 1, and print each
    model's prediction error (MSE, m^2) per drone on the held-out last 20 % of the recording.
    `track` does this on demand; a model already in --out is kept, one stopped early goes on
    from its last round.

    Example: dronefl pretrain --scenario case2 --setting paper --out runs/pretrained
    """
    from dronefl.experiments.prepare import prepare
    from dronefl.experiments.pretrain import KINDS, held_out_mse

    spec = load_scenario(scenario)
    chosen = _setting(setting, set_)
    for kind in (k for k in KINDS if image or k != "image"):
        prepared = prepare(spec, chosen, kind, out)
        try:
            per_drone = held_out_mse(prepared.spec, out)
        except ValueError as exc:  # no drone evaluated: every update failed (logged above)
            raise fail(f"pretraining {kind}: {exc}") from None
        mean = sum(per_drone.values()) / len(per_drone)
        errors = " / ".join(f"{v:.3g}" for v in per_drone.values())
        gaps = "" if kind == "image" else f", detection gaps {prepared.spec.detection_gaps:g}"
        typer.echo(
            f"{kind:12s} held-out MSE {mean:.4g} m^2 "
            f"(drones {' / '.join(map(str, per_drone))}: {errors}{gaps})"
        )
        typer.echo(f"wrote {prepared.spec.model_path(out)}")


@app.command()
def reproduce(
    artefact: Annotated[
        str, typer.Argument(help="fig4 | fig5 | table1 | table2 | all (the paper's artefacts).")
    ],
    out: OutOption = Path("runs/reproduce"),
    quick: Annotated[
        bool,
        typer.Option("--quick", help="A smoke run of minutes: one seed, few rounds, short runs."),
    ] = False,
    pretrained: Annotated[
        Path | None,
        typer.Option(help="Cache of pretrained models (default: OUT/pretrained)."),
    ] = None,
) -> None:
    """Reproduce a paper artefact exactly as the README reports it (Fig. 5's per-case training
    included), resuming from what OUT holds; writes OUT/ARTEFACT/ARTEFACT.md with ours beside
    the paper's, and the plots.

    Example: dronefl reproduce table1 --out runs/reproduce
    """
    from dronefl.reproduce import ARTEFACTS
    from dronefl.reproduce import reproduce as run

    check_choice(artefact, (*ARTEFACTS, "all"), "ARTEFACT")
    if pretrained is not None:
        writable_folder(pretrained)
    written = run(artefact, out, quick=quick, pretrained=pretrained)
    typer.echo(written.read_text() if written.is_file() else "")
    typer.echo(f"wrote {written}")


setting_app = typer.Typer(no_args_is_help=True, help="Settings: show one, resolved.")
app.add_typer(setting_app, name="setting")


@setting_app.command("show")
def setting_show(
    name: Annotated[
        str, typer.Argument(help="A named setting (recommended, paper) or a TOML file.")
    ] = "recommended",
    set_: SetOption = None,
    toml: Annotated[bool, typer.Option("--toml", help="Print it as a TOML file instead.")] = False,
) -> None:
    """Print a setting, resolved (a file's base and the --set overrides applied), with each
    field's documentation; --toml prints a file to start your own from.

    Example: dronefl setting show paper --set fusion.method=robust
    """
    chosen = _setting(name, set_)
    typer.echo(chosen.to_toml() if toml else chosen.describe())


@app.command()
def replay(
    episode: Annotated[
        Path, typer.Argument(help="A `dronefl track` or `dronefl deploy up` folder (episode.npz).")
    ],
    as_flown: Annotated[
        bool,
        typer.Option(
            "--as-flown",
            help="Start from the setting the episode was flown with (its metrics.json); --set "
            "changes fields of it.",
        ),
    ] = False,
    setting: SettingOption = "recommended",
    set_: SetOption = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Folder for replay.json/.md.")] = (
        None
    ),
) -> None:
    """Re-fuse and smooth an episode's recorded predictions as another setting's cloud would;
    print, per target, each drone's prediction MSE beside the fused track's and the labels'.
    What the setting has the drones send beyond what they sent (noise reports, the bias
    correction) is rebuilt from their records. A `deploy up` folder replays what its cloud
    received.

    Example: dronefl replay runs/c2 --as-flown --set fusion.method=paper --out runs/c2/replay
    """
    from dronefl.experiments.replay import (
        EpisodeError,
        format_result,
        load_episode,
        replay_setting,
        write_result,
    )
    from dronefl.settings import SettingError

    if out is not None:
        writable_folder(out)
    try:
        recorded = load_episode(episode)
        if as_flown:
            if recorded.setting is None:
                raise EpisodeError(f"{episode}/metrics.json: records no setting to replay as flown")
            chosen = recorded.setting.override(set_ or ())
        else:
            chosen = _setting(setting, set_)
        result = replay_setting(recorded, chosen)
    except (EpisodeError, SettingError, ValueError) as exc:
        raise fail(str(exc)) from None
    typer.echo(format_result(result))
    if out is not None:
        write_result(result, out)
        typer.echo(f"wrote {out}/ (replay.json, replay.md)")


# -- deployment: the same loop as separate processes (dronefl.deploy) ------------------------

deploy_app = typer.Typer(
    no_args_is_help=True, help="Deployment on one machine: all processes, certificates."
)
app.add_typer(deploy_app, name="deploy")
StartTimeoutOption = Annotated[
    float, typer.Option("--start-timeout", help="Seconds to wait for the other processes.")
]
TlsDirOption = Annotated[
    str, typer.Option("--tls-dir", help="Folder of `dronefl deploy certs` (TLS, access control).")
]
InsecureOption = Annotated[
    bool, typer.Option("--insecure", help="Plain TCP, no authentication (instead of --tls-dir).")
]
ModelOption = Annotated[Path, typer.Option("--model", help="Model weights file (by path).")]


@contextmanager
def _deploy_errors() -> Iterator[None]:
    """Run a deployment command: Ctrl-C or SIGTERM stops its children and ends it with one line;
    a bad setup (code 2) or a failure at run time (code 1) is one line, never a traceback."""
    from dronefl.deploy import CloudError
    from dronefl.deploy.link import LinkError
    from dronefl.deploy.processes import DeployError
    from dronefl.deploy.world import WorldError

    try:
        yield
    except (ValueError, FileNotFoundError, ScenarioError) as exc:
        raise fail(str(exc)) from None
    except (DeployError, LinkError, WorldError, CloudError) as exc:
        typer.secho(f"error: {exc}", err=True, fg="red")
        raise typer.Exit(code=1) from None
    except KeyboardInterrupt:
        cause = "terminated (SIGTERM)" if TERMINATED.is_set() else "interrupted"
        typer.secho(f"{cause}; every process started was stopped", err=True)
        raise typer.Exit(code=TERMINATED_CODE if TERMINATED.is_set() else INTERRUPTED) from None


def _endpoints(text: str) -> tuple[str, ...]:
    return tuple(e.strip() for e in text.split(",") if e.strip())


@app.command()
def world(
    scenario: ScenarioOption = "case1",
    duration: Annotated[float, typer.Option(help="Simulated seconds.")] = 120.0,
    seed: SeedOption = 0,
    env: Annotated[str, typer.Option("--env", help="Environment.")] = "orchard",
    listen: Annotated[str, typer.Option(help="Zenoh endpoint host:port.")] = "127.0.0.1:7440",
    grace_ms: Annotated[float, typer.Option(help="Wall ms a control may be late.")] = 150.0,
    start_timeout: StartTimeoutOption = 120.0,
    tls_dir: TlsDirOption = "",
    insecure: InsecureOption = False,
    out: OutOption = Path("runs/deploy/world"),
) -> None:
    """The simulator of a deployment: owns the clock, publishes every drone's sensors over
    Zenoh and applies the controls it receives. Writes world.npz.

    Example: dronefl world --scenario case1 --duration 120 --listen 0.0.0.0:7440 --tls-dir certs
    """
    from dronefl.deploy import INSECURE_WARNING, check_security
    from dronefl.deploy.world import WorldSettings, run_world

    check_choice(env, ENVIRONMENTS, "--env")
    with _deploy_errors():
        check_security(tls_dir, insecure)
        load_scenario(scenario)
        settings = WorldSettings(
            scenario, out, seed, duration, env, listen, tls_dir, start_timeout, grace_ms=grace_ms
        )
        if insecure:
            typer.secho(INSECURE_WARNING, err=True, fg="yellow")
        run_world(settings)


@app.command()
def drone(
    drone_id: Annotated[int, typer.Option("--id", help="Drone id in the scenario.")],
    model: ModelOption,
    scenario: ScenarioOption = "case1",
    setting: SettingOption = "recommended",
    set_: SetOption = None,
    connect: Annotated[
        str, typer.Option(help="Zenoh endpoints of the world and the cloud, comma-separated.")
    ] = "127.0.0.1:7440,127.0.0.1:7441",
    superlink: Annotated[str, typer.Option(help="SuperLink host:port.")] = "127.0.0.1:7442",
    runtime_port: Annotated[int, typer.Option(help="SuperNode's local runtime port.")] = 7450,
    data_dir: Annotated[Path, typer.Option(help="The drone's disk.")] = Path("runs/deploy/drone"),
    start_timeout: StartTimeoutOption = 120.0,
    tls_dir: TlsDirOption = "",
    insecure: InsecureOption = False,
) -> None:
    """One drone: predictor on ONNX Runtime, onboard record on its disk, predictions up and
    controls down over Zenoh, and a Flower SuperNode that trains on that disk. What it sends
    is the setting's [drone] (give every process of a deployment the same setting file).

    Example: dronefl drone --id 1 --model pretrained.npz --setting s.toml --tls-dir certs
    """
    from dronefl.deploy import INSECURE_WARNING, check_security
    from dronefl.deploy.drone import DroneSettings, run_drone

    chosen = _setting(setting, set_)
    with _deploy_errors():
        check_security(tls_dir, insecure)
        spec = load_scenario(scenario)
        if drone_id not in spec.drone_ids:
            raise ValueError(
                f"--id: drone {drone_id} is not in scenario {spec.name} "
                f"(drones {', '.join(map(str, spec.drone_ids))})"
            )
        if not model.is_file():
            raise FileNotFoundError(f"--model: {model} does not exist")
        settings = DroneSettings(
            scenario, drone_id, model, data_dir, chosen, _endpoints(connect), superlink,
            runtime_port, tls_dir, start_timeout,
        )  # fmt: skip
        if insecure:
            typer.secho(INSECURE_WARNING, err=True, fg="yellow")
        run_drone(settings, data_dir / "logs")


@app.command()
def cloud(
    model: ModelOption,
    scenario: ScenarioOption = "case1",
    setting: SettingOption = "recommended",
    set_: SetOption = None,
    method: Annotated[str, typer.Option(help="dronefl|fixed")] = "dronefl",
    duration: Annotated[float, typer.Option(help="Simulated seconds.")] = 120.0,
    seed: SeedOption = 0,
    deadline_ms: Annotated[float, typer.Option(help="Wall ms to wait for predictions.")] = 150.0,
    listen: Annotated[str, typer.Option(help="Zenoh endpoint host:port.")] = "127.0.0.1:7441",
    connect: Annotated[str, typer.Option(help="The world's Zenoh endpoint.")] = "127.0.0.1:7440",
    superlink_host: Annotated[str, typer.Option(help="SuperLink address.")] = "127.0.0.1",
    superlink_port: Annotated[int, typer.Option(help="SuperLink port.")] = 7442,
    start_timeout: StartTimeoutOption = 120.0,
    tls_dir: TlsDirOption = "",
    insecure: InsecureOption = False,
    out: OutOption = Path("runs/deploy/cloud"),
) -> None:
    """The cloud: a Flower SuperLink and, launched with `flwr run` against it, the ServerApp
    that fuses, plans and plays an FL round every learning.period s. Writes cloud.npz/json.

    The model file must hold the model the setting trains (`dronefl deploy up` writes it).

    Example: dronefl cloud --model pretrained.npz --superlink-host 0.0.0.0 --tls-dir certs
    """
    from dronefl.deploy import INSECURE_WARNING, check_security
    from dronefl.deploy.clientapp import load_model
    from dronefl.deploy.cloud import CloudSettings
    from dronefl.deploy.superlink import SuperLinkSettings, run_cloud
    from dronefl.fl.records import online_settings

    chosen = _setting(setting, set_)
    with _deploy_errors():
        check_security(tls_dir, insecure)
        spec = load_scenario(scenario)
        if not model.is_file():
            raise FileNotFoundError(f"--model: {model} does not exist")
        out = out.resolve()
        settings = CloudSettings(
            scenario=scenario,
            model=str(model.resolve()),
            out=str(out),
            setting=chosen.to_toml(),
            method=method,
            duration=duration,
            deadline_ms=deadline_ms,
            listen=listen,
            connect=connect,
            tls_dir=str(Path(tls_dir).resolve()) if tls_dir else "",
            start_timeout=start_timeout,
        )
        field_m = (spec.field.width, spec.field.height)
        fl = online_settings(
            chosen, "dronefl", seed, field_m, str(out / "fl"), str(out / "fl" / "global")
        )
        if load_model(model).model != fl.model:
            raise ValueError(
                f"--model: {model} holds another model than the setting trains (give the "
                "setting it was pretrained with)"
            )
        link = SuperLinkSettings(superlink_host, superlink_port, start_timeout)
        if insecure:
            typer.secho(INSECURE_WARNING, err=True, fg="yellow")
        run_cloud(settings, fl, link, out / "logs")


@deploy_app.command("up")
def deploy_up(
    scenario: ScenarioOption = "case2",
    method: Annotated[str, typer.Option(help="dronefl|fixed")] = "dronefl",
    seed: SeedOption = 0,
    duration: Annotated[float, typer.Option(help="Simulated seconds.")] = 120.0,
    env: Annotated[str, typer.Option("--env", help="Environment.")] = "orchard",
    setting: SettingOption = "recommended",
    set_: SetOption = None,
    pretrained: Annotated[Path, typer.Option(help="Cache of pretrained models.")] = Path(
        "runs/pretrained"
    ),
    insecure: Annotated[
        bool,
        typer.Option("--insecure", help="Plain TCP, no authentication (default: TLS, ACL)."),
    ] = False,
    certs: Annotated[
        Path | None, typer.Option(help="Certificate folder (default: a fresh one in --out).")
    ] = None,
    base_port: Annotated[int, typer.Option(help="First of the deployment's ports.")] = 7440,
    deadline_ms: Annotated[float, typer.Option(help="Wall ms to wait for predictions.")] = 150.0,
    start_timeout: StartTimeoutOption = 120.0,
    restart_drones: Annotated[bool, typer.Option(help="Restart a drone that dies.")] = False,
    out: OutOption = Path("runs/deploy"),
) -> None:
    """Run the world, every drone (+ SuperNode) and the cloud (SuperLink + ServerApp) as
    separate processes on 127.0.0.1, all with the same setting (written to OUT/setting.toml);
    writes metrics.json and logs/ (one log per process). Secure unless --insecure: mutual TLS
    and access control on every link, SuperNode authentication (certificates: --certs or
    fresh ones in OUT/certs).

    Example: dronefl deploy up --scenario case2 --duration 600 --out runs/deploy
    """
    from dronefl.deploy import INSECURE_WARNING
    from dronefl.deploy.launcher import DeployConfig, preflight, run_deploy
    from dronefl.experiments.prepare import prepare

    chosen = _setting(setting, set_)
    with _deploy_errors():
        config = DeployConfig(
            scenario=scenario, out=out, setting=chosen, method=method, duration=duration,
            seed=seed, environment=env, insecure=insecure, certs=certs, base_port=base_port,
            deadline_ms=deadline_ms, start_timeout=start_timeout, pretrained=pretrained,
            restart_drones=restart_drones,
        )  # fmt: skip
        spec = preflight(config)  # ports and certificates, before any work
        if insecure:
            typer.secho(INSECURE_WARNING, err=True, fg="yellow")
        prepared = prepare(spec, chosen, "dronefl", pretrained, progress=False)
        metrics = run_deploy(config, prepared.state, prepared.spec.model)
    from dronefl.report.tables import format_metrics  # heavy (the closed loop's tables)

    typer.echo(format_metrics(metrics))
    typer.echo(f"wrote {out}/metrics.json and {out}/logs/ ({len(metrics.fl_rounds)} FL rounds)")


@deploy_app.command("report")
def deploy_report(
    world_dir: Annotated[Path, typer.Option("--world", help="Folder with the world's world.npz.")],
    cloud_dir: Annotated[Path, typer.Option("--cloud", help="Folder with cloud.npz/json.")],
    scenario: ScenarioOption = "case1",
    out: OutOption = Path("runs/deploy"),
) -> None:
    """Join the world's and the cloud's logs of a multi-host episode into metrics.json.

    Example: dronefl deploy report --world runs/world --cloud runs/cloud --out runs/episode
    """
    import numpy as np

    from dronefl.deploy.results import CloudLog, RunInfo, deployment_metrics

    with _deploy_errors():
        spec = load_scenario(scenario)
        for path in (world_dir / "world.npz", cloud_dir / "cloud.npz", cloud_dir / "cloud.json"):
            if not path.is_file():
                raise FileNotFoundError(f"{path} does not exist")
        settings = CloudLog.load(cloud_dir / "cloud.json").settings
        with np.load(world_dir / "world.npz", allow_pickle=False) as world:
            seed, environment = int(world["seed"]), str(world["environment"])
        run = RunInfo(str(settings["method"]), seed, environment, dict(settings))
        deployment_metrics(spec, world_dir, cloud_dir, out, run).save(out / "metrics.json")
    typer.echo(f"wrote {out}/metrics.json and {out}/episode.npz")


@deploy_app.command("certs")
def deploy_certs(
    folder: Annotated[Path, typer.Argument(help="Folder to write.")],
    scenario: ScenarioOption = "case1",
    hosts: Annotated[
        str, typer.Option(help="Hosts the certificates name, comma-separated.")
    ] = "127.0.0.1,localhost",
) -> None:
    """A CA, the SuperLink's and every process's TLS certificates, one SuperNode key pair per
    drone of the scenario.

    Example: dronefl deploy certs runs/certs --scenario case1 --hosts 10.0.0.5,cloud.local
    """
    from dronefl.deploy.certs import make_certificates

    spec = load_scenario(scenario)
    try:
        make_certificates(folder, spec.drone_ids, _endpoints(hosts))
    except (ValueError, OSError) as exc:
        raise fail(f"FOLDER: {exc}") from None
    typer.echo(f"wrote {folder}/ (ca.crt, superlink.crt, zenoh-*.crt, supernode-<id>[.pub])")


app.command("bench")(bench_command)


def _terminate(_signum: int, frame: object) -> None:
    """SIGTERM: stop exactly as Ctrl-C does, through the SIGINT handler in place (the
    simulation engine's notes the interrupt, so that its threads and Ray are ended), and note
    that it was SIGTERM, for the exit code and the last line."""
    TERMINATED.set()
    handler = signal.getsignal(signal.SIGINT)
    if not callable(handler):  # SIGINT ignored or not set from Python: SIGTERM still stops
        handler = signal.default_int_handler
    handler(signal.SIGINT, frame)


def main() -> None:
    """Entry point with bad-input errors turned into one line and exit code 2, a failed
    training run into one line and exit code 1, Ctrl-C into one line and exit code 130, and
    SIGTERM into one line and exit code 143; never hangs at exit (see :func:`leave`)."""
    signal.signal(signal.SIGTERM, _terminate)
    try:
        app()
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        if code == INTERRUPTED:
            cause = "terminated (SIGTERM)" if TERMINATED.is_set() else "interrupted"
            typer.secho(
                f"{cause}: finished rounds and episodes are kept; --resume continues",
                err=True,
                fg="red",
            )
            code = TERMINATED_CODE if TERMINATED.is_set() else INTERRUPTED
        leave(code)
    except USER_ERRORS as exc:
        leave(fail(str(exc)).exit_code)
    except TrainingError as exc:  # a run that failed (logged above): one line, exit code 1
        fail(str(exc))
        leave(1)
    leave(0)


def leave(code: int) -> NoReturn:
    """Exit with ``code``, also after Ctrl-C in a federated round.

    Flower's simulation engine, stopped by Ctrl-C, has killed its actors but leaves Ray up and
    its worker threads (not daemons) ending, and the interpreter could wait on threads that
    never end (:data:`dronefl.fl.simulation.ENGINE_INTERRUPTED`). Then the threads get
    :data:`EXIT_GRACE_S` s to finish, Ray is shut down (only after them: a thread touching Ray
    after its shutdown makes Ray end the process with exit code 1), and the process ends at
    once. Results and checkpoints are written atomically, so nothing
    half-written is left."""
    simulation = sys.modules.get("dronefl.fl.simulation")
    if simulation is None or not simulation.ENGINE_INTERRUPTED.is_set():
        raise SystemExit(code)
    main_thread = threading.main_thread()
    deadline = time.monotonic() + EXIT_GRACE_S
    for thread in threading.enumerate():
        if thread is not main_thread and not thread.daemon:
            thread.join(max(0.0, deadline - time.monotonic()))
    ray = sys.modules.get("ray")
    if ray is not None and ray.is_initialized():
        ray.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    main()
