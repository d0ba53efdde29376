"""Results as typed objects, serialised to JSON in this one place.

Every result that crosses a module boundary (an episode's metrics, an FL round of the closed
loop, the traffic of a run, ...) is a frozen dataclass with its units in its field docs.
:func:`to_json` turns such a dataclass into plain JSON values and :func:`from_json` builds it
back from them, guided by the dataclass' type hints: nested dataclasses, tuples, dicts (JSON
keys are strings; ``dict[int, ...]`` keys are turned back into ints), optional fields and
:class:`~pathlib.Path` values. A field made with :func:`omitted_when_none` is left out of the
JSON while it is None (a key that only some objects carry); one made with :func:`json_key` is
stored under a key that is no Python name (``"mAP50-95"``). :func:`save_result` /
:func:`load_result` write and read them atomically, and a file that does not hold the expected
object raises :class:`ResultError` naming the file.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from dronefl.io import atomic_write_json

T = TypeVar("T")
#: Field metadata key of :func:`omitted_when_none`.
_OMIT_NONE = "dronefl.serialize.omit_none"
#: Field metadata key of :func:`json_key`.
_JSON_KEY = "dronefl.serialize.json_key"


class ResultError(ValueError):
    """A results file that is missing, corrupt or of another kind."""


def omitted_when_none() -> Any:
    """A dataclass field defaulting to None that :func:`to_json` leaves out while it is None;
    :func:`from_json` gives None where its key is absent."""
    return dataclasses.field(default=None, metadata={_OMIT_NONE: True})


def json_key(key: str) -> Any:
    """A dataclass field (without default) that :func:`to_json` writes under the JSON key
    ``key`` instead of its name, and :func:`from_json` reads from there."""
    return dataclasses.field(metadata={_JSON_KEY: key})


def _key(field: dataclasses.Field) -> str:
    return field.metadata.get(_JSON_KEY, field.name)


def to_json(value: Any) -> Any:
    """Plain JSON values for ``value`` (dataclasses become objects, tuples lists, Paths
    strings, non-finite floats ``None``)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            _key(f): to_json(getattr(value, f.name))
            for f in dataclasses.fields(value)
            if not (f.metadata.get(_OMIT_NONE) and getattr(value, f.name) is None)
        }
    if isinstance(value, dict):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_json(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def from_json(cls: type[T], data: Any) -> T:
    """The dataclass ``cls`` built from :func:`to_json`'s output ``data``."""
    return _build(cls, data, cls.__name__)


def save_result(path: Path, value: object) -> Path:
    """Write the dataclass ``value`` to ``path`` as JSON, atomically."""
    return atomic_write_json(Path(path), to_json(value))


def load_result(cls: type[T], path: Path) -> T:
    """Read a :func:`save_result` file as ``cls``; :class:`ResultError` names the file."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise ResultError(f"{path}: no such results file") from None
    except (OSError, ValueError) as exc:
        raise ResultError(f"{path}: not a JSON results file ({exc})") from None
    try:
        return from_json(cls, data)
    except (TypeError, ValueError, KeyError) as exc:
        raise ResultError(f"{path}: not a {cls.__name__} result ({exc})") from None


def _build(hint: Any, data: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        options = [a for a in typing.get_args(hint) if a is not type(None)]
        if data is None:
            return math.nan if float in options else None
        return _build(options[0], data, where)
    if dataclasses.is_dataclass(hint):
        if not isinstance(data, dict):
            raise TypeError(f"{where}: expected an object, got {type(data).__name__}")
        hints = typing.get_type_hints(hint)
        names = {_key(f): f.name for f in dataclasses.fields(hint) if f.init}
        unknown = set(data) - set(names)
        if unknown:
            raise KeyError(f"{where}: unknown field {sorted(unknown)[0]!r}")
        return hint(
            **{names[k]: _build(hints[names[k]], v, f"{where}.{k}") for k, v in data.items()}
        )
    if origin is tuple:
        args = typing.get_args(hint)
        item = args[0] if args else Any
        return tuple(_build(item, v, f"{where}[]") for v in _list(data, where))
    if origin is list:
        (item,) = typing.get_args(hint) or (Any,)
        return [_build(item, v, f"{where}[]") for v in _list(data, where)]
    if origin is dict:
        key, item = typing.get_args(hint) or (str, Any)
        if not isinstance(data, dict):
            raise TypeError(f"{where}: expected an object, got {type(data).__name__}")
        return {
            (int(k) if key is int else k): _build(item, v, f"{where}.{k}") for k, v in data.items()
        }
    if hint is float:
        return math.nan if data is None else float(data)
    if hint is int:
        if isinstance(data, bool) or not isinstance(data, int):
            raise TypeError(f"{where}: expected an integer, got {data!r}")
        return data
    if hint is Path:
        return Path(data)
    return data


def _list(data: Any, where: str) -> list:
    if not isinstance(data, list):
        raise TypeError(f"{where}: expected a list, got {type(data).__name__}")
    return data
