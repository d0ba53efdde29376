"""The checks every configuration makes of what a user gives, each with one message for all
commands: a named choice (``--option: 'x' is not one of a, b, c``), a duration, a seed and a
positive quantity, each naming the option as the user wrote it."""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable

#: The longest run any command flies or records, s (one day).
MAX_DURATION_S = 86400.0
#: Seeds are 32-bit (numpy's ``SeedSequence`` entropy and Flower's run ids take them whole).
SEED_LIMIT = 2**32


def check_one_of(value: object, choices: Collection[str], option: str) -> None:
    """Raise ``ValueError`` naming ``option`` (as the user wrote it, e.g. ``--method``)
    unless ``value`` is one of ``choices`` (a tuple, or a registry dict's keys)."""
    if value not in choices:
        raise ValueError(f"{option}: {value!r} is not one of {', '.join(choices)}")


def check_duration(value: float, shortest: float, option: str = "--duration") -> None:
    """``ValueError`` naming ``option`` unless ``value`` (s) is finite and in
    [``shortest``, :data:`MAX_DURATION_S`] (``shortest``: one step, or what a run needs)."""
    if not (math.isfinite(value) and shortest <= value <= MAX_DURATION_S):
        raise ValueError(
            f"{option}: must be between {shortest:g} s and {MAX_DURATION_S:g} s, got {value}"
        )


def check_seeds(seeds: Iterable[int], option: str = "--seed") -> None:
    """``ValueError`` naming ``option`` unless every seed is in [0, 2^32)."""
    bad = [s for s in seeds if not 0 <= s < SEED_LIMIT]
    if bad:
        raise ValueError(f"{option}: must be in [0, 2^32), got {bad[0]}")


def check_positive(value: float, option: str) -> None:
    """``ValueError`` naming ``option`` unless ``value`` is finite and > 0."""
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{option}: must be finite and positive, got {value}")
