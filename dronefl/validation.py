"""The check every configuration makes of a named choice, with one message for all of them
(``--option: 'x' is not one of a, b, c``)."""

from __future__ import annotations

from collections.abc import Collection


def check_one_of(value: object, choices: Collection[str], option: str) -> None:
    """Raise ``ValueError`` naming ``option`` (as the user wrote it, e.g. ``--method``)
    unless ``value`` is one of ``choices`` (a tuple, or a registry dict's keys)."""
    if value not in choices:
        raise ValueError(f"{option}: {value!r} is not one of {', '.join(choices)}")
