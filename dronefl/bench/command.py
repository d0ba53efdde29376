"""The ``dronefl bench`` command (registered in :mod:`dronefl.cli`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def bench(
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Folder for bench.json and bench.md.")
    ] = Path("runs/bench"),
    quick: Annotated[
        bool,
        typer.Option("--quick", help="Shrunk sizes (seconds, not minutes); not representative."),
    ] = False,
    only: Annotated[
        str,
        typer.Option(
            "--only", help="Comma-separated groups: cloud,simulator,predictor,vision,closed_loop."
        ),
    ] = "",
    pretrained: Annotated[
        Path, typer.Option("--pretrained", help="Pretrained models for the closed loop (cached).")
    ] = Path("runs/pretrained"),
    scenario: Annotated[
        str, typer.Option("--scenario", "-s", help="Built-in scenario or YAML path.")
    ] = "case3",
) -> None:
    """Run every performance benchmark and write DIR/bench.json and DIR/bench.md (figures with
    their threads and references, goals, energy estimates, Table II beside the paper's).

    Example: dronefl bench --out runs/bench        dronefl bench --quick --only cloud,predictor
    """
    from dronefl.bench.run import BenchError, run_bench
    from dronefl.config import load_scenario

    spec = load_scenario(scenario)
    groups = tuple(g.strip() for g in only.split(",") if g.strip())
    try:
        results = run_bench(out, quick=quick, only=groups, pretrained=pretrained, scenario=spec)
    except BenchError as exc:
        typer.secho(f"error: {exc}", err=True, fg="red")
        raise typer.Exit(code=2) from None
    met = [g.met for g in results.goals if g.met is not None]
    typer.echo(f"goals met: {sum(met)} of {len(met)} measured")
    typer.echo(f"wrote {out}/bench.json and {out}/bench.md")
