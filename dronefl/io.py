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
import math
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
    """Write ``obj`` as indented JSON to ``path`` atomically. A non-finite float (an MSE of
    no sample, a ratio to zero) becomes ``null``: JSON has no NaN, and other readers reject
    Python's ``NaN``."""
    text = json.dumps(_finite(obj), indent=2, sort_keys=False, allow_nan=False)
    return atomic_write_text(path, text + "\n")


def _finite(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    return obj


def atomic_savez(path: str | Path, **arrays: np.ndarray) -> Path:
    """``np.savez_compressed`` to ``path`` atomically."""
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    return atomic_write_bytes(path, buffer.getvalue())


#: The key of a state file's structure (JSON) among its arrays.
_TREE = "__tree__"


class StateFileError(ValueError):
    """A state file that is missing, truncated, corrupt or not a state file (names it)."""


def save_state(path: str | Path, tree: Any) -> Path:
    """Write ``tree`` atomically as a state file: ``.npz`` with every array of the tree and its
    structure as JSON, readable with ``allow_pickle=False`` (nothing in it can run code).

    ``tree`` is made of dicts (any hashable keys of the kinds below), lists, tuples, ``None``,
    bools, ints, floats (non-finite too), strings and numpy arrays (numpy scalars are stored as
    Python numbers); anything else is a ``TypeError``. :func:`load_state` gives it back equal,
    tuples as tuples and every float to the bit."""
    arrays: dict[str, np.ndarray] = {}
    text = json.dumps(_encode(tree, arrays), allow_nan=True)
    return atomic_savez(path, **{_TREE: np.array(text)}, **arrays)


def load_state(path: str | Path) -> Any:
    """The tree a :func:`save_state` file holds; :class:`StateFileError` naming the file when
    it is not one."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
        tree = json.loads(str(arrays.pop(_TREE)))
        return _decode(tree, arrays)
    except FileNotFoundError:
        raise StateFileError(f"{path}: not found") from None
    except Exception as exc:  # a damaged zip or JSON raises its own errors: all mean corrupt
        raise StateFileError(
            f"{path}: truncated or corrupt state file ({type(exc).__name__})"
        ) from None


def _encode(value: Any, arrays: dict[str, np.ndarray]) -> Any:
    if isinstance(value, np.ndarray):
        if value.dtype == object:
            raise TypeError("save_state: arrays of Python objects cannot be stored")
        key = f"a{len(arrays)}"
        arrays[key] = value
        return {"__array__": key}
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, tuple):
        return {"__tuple__": [_encode(v, arrays) for v in value]}
    if isinstance(value, list):
        return [_encode(v, arrays) for v in value]
    if isinstance(value, dict):
        return {"__dict__": [[_encode(k, arrays), _encode(v, arrays)] for k, v in value.items()]}
    raise TypeError(f"save_state: cannot store a {type(value).__name__}")


def _decode(value: Any, arrays: dict[str, np.ndarray]) -> Any:
    if isinstance(value, list):
        return [_decode(v, arrays) for v in value]
    if not isinstance(value, dict):
        return value
    if "__array__" in value:
        return arrays[value["__array__"]]
    if "__tuple__" in value:
        return tuple(_decode(v, arrays) for v in value["__tuple__"])
    return {_decode(k, arrays): _decode(v, arrays) for k, v in value["__dict__"]}
