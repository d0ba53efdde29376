"""Helpers of the deployment tests: free ports, command lines, surviving processes."""

from __future__ import annotations

import socket
import sys
from pathlib import Path

import psutil

ROOT = Path(__file__).resolve().parents[2]
#: Every process a test starts carries this variable (value: the test's own id), so that the
#: test can check that none of *its* processes survived (other people's are never looked at).
MARK = "DRONEFL_TEST_MARK"


def free_port_block(size: int = 20) -> int:
    """A base port with ``size`` free ports above it (on 127.0.0.1)."""
    for _ in range(200):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            base = s.getsockname()[1]
        if base + size > 65000:
            continue
        if all(_free(base + k) for k in range(size)):
            return base
    raise RuntimeError("no block of free ports")


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
