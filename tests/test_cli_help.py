"""Every command documents its arguments in ``--help``: Click 8.5 overwrote the help text
Typer 0.20 gives a positional argument (its ``Argument`` learnt a ``help`` of its own), so
``--help`` listed every argument without a word; Click is pinned below that (constraints)."""

import typer
from typer.core import TyperArgument
from typer.testing import CliRunner

from dronefl.cli import app


def _commands_with_argument_help() -> list[tuple[str, str]]:
    group = typer.main.get_command(app)
    found = []
    for name, command in group.commands.items():  # type: ignore[attr-defined]
        for param in command.params:
            if isinstance(param, TyperArgument) and param.help:
                found.append((name, param.help))
    return found


def test_every_argument_s_help_is_shown():
    documented = _commands_with_argument_help()
    assert len(documented) >= 5  # replay, fl-compare, table1-compare, ...
    runner = CliRunner(env={"COLUMNS": "250"})
    for name, text in documented:
        shown = runner.invoke(app, [name, "--help"])
        assert shown.exit_code == 0, shown.output
        first_words = " ".join(text.split()[:3])
        assert first_words in " ".join(shown.output.split()), (name, text)


def test_the_closed_loop_commands_fit_on_a_screen():
    # Every knob of the method is in the setting (--setting, --set), not an option.
    runner = CliRunner(env={"COLUMNS": "100"})
    for command, most in ((["track"], 40), (["table1"], 40), (["deploy", "up"], 60)):
        shown = runner.invoke(app, [*command, "--help"])
        assert shown.exit_code == 0, shown.output
        assert len(shown.output.splitlines()) <= most, (command, shown.output)
        assert "--set " in shown.output and "--setting" in shown.output
