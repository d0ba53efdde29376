"""The ``dronefl`` command. Every sub-command validates its inputs before doing any work and
exits with code 2 and one line naming the bad file/field on bad input."""

from __future__ import annotations

import typer

from dronefl.config import ScenarioError
from dronefl.logs import LogError

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


def main() -> None:
    """Entry point with bad-input errors turned into one line and exit code 2."""
    try:
        app()
    except USER_ERRORS as exc:
        raise SystemExit(fail(str(exc)).exit_code) from None
