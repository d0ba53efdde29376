"""The ``dronefl`` command. Every sub-command validates its inputs before doing any work and
exits with code 2 and one line naming the bad file/field on bad input."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from dronefl.config import ENVIRONMENTS, ScenarioError, builtin_scenarios, load_scenario
from dronefl.logs import LogError
from dronefl.perception import DETECTORS

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="DroneFL: federated learning for multi-drone visual target tracking.",
)

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
SeedOption = Annotated[int, typer.Option("--seed", help="Random seed of the run.")]
OutOption = Annotated[Path, typer.Option("--out", "-o", help="Run folder to write.")]


def check_choice(value: str | None, choices: tuple[str, ...], option: str) -> None:
    """Reject ``value`` unless it is one of ``choices`` (None passes)."""
    if value is not None and value not in choices:
        raise fail(f"{option}: {value!r} is not one of {', '.join(choices)}")


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
    if duration <= 0:
        raise fail(f"--duration: must be positive, got {duration}")
    spec = load_scenario(scenario)
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
def demo(out: OutOption = Path("runs/demo")) -> None:
    """The default experiment: record Case 3 in the crop field for 120 s and plot it.

    Example: dronefl demo --out runs/demo
    """
    from dronefl.experiments.simulate import format_summary
    from dronefl.experiments.simulate import simulate as run

    summary = run(load_scenario("case3"), duration=120.0, seed=0, out=out / "simulate")
    typer.echo(format_summary(summary))
    typer.echo(f"wrote {out}/simulate/topdown.png")


def main() -> None:
    """Entry point with bad-input errors turned into one line and exit code 2."""
    try:
        app()
    except USER_ERRORS as exc:
        raise SystemExit(fail(str(exc)).exit_code) from None
