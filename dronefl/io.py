"""Atomic, durable file writes: a reader (or a killed run) never sees a half-written result.

Each writer writes to a temporary file in the destination folder, flushes it to disk
(``fsync``), renames it onto the final name with ``os.replace`` (atomic on POSIX file systems)
and flushes the folder, so that the new name survives a power cut too.

Crash points (for the kill tests): with ``DRONEFL_CRASH_AT=NAME[@N]`` in the environment the
process sends itself ``SIGKILL`` the ``N``-th time (default: first) it passes the point
``NAME``. The writers pass ``write:<file name>`` after the temporary file is complete and
before it replaces the old one (a kill mid-write); the FL round loop passes ``round-end:<k>``
after round ``k`` trained and evaluated, before it is recorded (a kill mid-round).
"""

from __future__ import annotations

import io
import json
import os
import signal
import tempfile
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

import numpy as np

#: Environment variable naming the crash point (``NAME`` or ``NAME@N``).
CRASH_ENV = "DRONEFL_CRASH_AT"
_passed: Counter[str] = Counter()


def crash_point(name: str) -> None:
    """``SIGKILL`` this process if ``DRONEFL_CRASH_AT`` names this pass of point ``name``."""
    wanted = os.environ.get(CRASH_ENV)
    if not wanted:
        return
    point, _, nth = wanted.partition("@")
    if point != name:
        return
    _passed[name] += 1
    if _passed[name] == int(nth or 1):
        os.kill(os.getpid(), signal.SIGKILL)


def _atomic_write(path: Path, write: Callable[[IO[bytes]], None]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        crash_point(f"write:{path.name}")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    _fsync_folder(path.parent)
    return path


def _fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (a no-op where folders cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    return _atomic_write(Path(path), lambda f: f.write(data))


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode())


def atomic_write_json(path: str | Path, obj: Any) -> Path:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False) + "\n")


def atomic_savez(path: str | Path, **arrays: np.ndarray) -> Path:
    """``np.savez_compressed`` to ``path`` atomically."""
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    return atomic_write_bytes(path, buffer.getvalue())
