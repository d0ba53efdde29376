"""Running ``dronefl`` from a test: :func:`run_cli` in the test's own process, and
:func:`run_dronefl`, the child process of the ``cli_process`` fixture (``tests/conftest.py``),
in a module of its own: the fork server finds a child's function by module name, and every
test folder's ``conftest`` shares one."""

import os
import sys


def run_dronefl(argv: list[str], crash_at: str | None) -> None:
    """``dronefl ARGV`` with ``DRONEFL_CRASH_AT=crash_at`` when given (:mod:`dronefl.io`)."""
    from dronefl.cli import main
    from dronefl.io import CRASH_ENV

    os.environ.pop(CRASH_ENV, None)
    if crash_at:
        os.environ[CRASH_ENV] = crash_at
    sys.argv = ["dronefl", *argv]
    main()


def run_cli(capsys, *argv: str) -> tuple[int, str]:
    """``dronefl ARGV`` in this process; returns the exit code and what went to stderr."""
    from dronefl.cli import main

    old, sys.argv = sys.argv, ["dronefl", *argv]
    try:
        main()
        code = 0
    except SystemExit as exc:
        code = exc.code
    finally:
        sys.argv = old
    return code, capsys.readouterr().err
