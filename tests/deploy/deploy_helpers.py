"""Helpers of the deployment tests: free ports, command lines, surviving processes."""

from __future__ import annotations

import os
import random
import socket
import subprocess
import sys
import time
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[2]
#: Every process a test starts carries this variable (value: the test's own id), so that the
#: test can check that none of *its* processes survived (other people's are never looked at).
MARK = "DRONEFL_TEST_MARK"


#: Where test deployments take their ports: above Ray's worker ports (10002-19999) and below
#: Linux's ephemeral range (from 32768), where any process's outgoing connection may take a
#: port between the check here and the deployment's bind (seen with tests run in parallel).
PORT_RANGE = (20000, 32760)


def free_port_block(size: int = 20) -> int:
    """A base port with ``size`` free ports above it (on 127.0.0.1), in this test worker's own
    stripe of :data:`PORT_RANGE` (pytest-xdist runs tests in parallel workers ``gw0``,
    ``gw1``, ...), so that two tests running at once never share a port."""
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
    workers = max(int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")), worker + 1)
    width = (PORT_RANGE[1] - PORT_RANGE[0]) // workers
    low = PORT_RANGE[0] + worker * width
    for _ in range(200):
        base = random.randrange(low, low + width - size)
        if all(_free(base + k) for k in range(size)):
            return base
    raise RuntimeError(f"no block of {size} free ports in {low}-{low + width}")


def _free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "dronefl.cli", *args]


def survivors(mark: str) -> list[str]:
    """Command lines of live processes carrying ``MARK=mark``."""
    left = []
    for process in psutil.process_iter():
        try:
            if process.environ().get(MARK) == mark and process.status() != "zombie":
                left.append(" ".join(process.cmdline())[:120])
        except psutil.Error:
            continue
    return left


def wait_for_line(path: Path, text: str, launcher: subprocess.Popen, seconds: float) -> None:
    """Wait until the file ``path`` holds ``text``; fail once ``launcher`` ends or ``seconds``
    pass."""
    deadline = time.monotonic() + seconds
    while not (path.is_file() and text in path.read_text()):
        assert launcher.poll() is None, f"the deployment ended before {text!r}"
        assert time.monotonic() < deadline, f"no {text!r} in {path} within {seconds:.0f} s"
        time.sleep(0.02)
