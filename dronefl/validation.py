"""The checks every configuration makes of a named choice, with one message for all of them
(``--option: 'x' is not one of a, b, c``), and of ``--pretrain-gaps``.

:class:`~dronefl.experiments.pretrain.PretrainSpec` keeps its own copy of the check: its
module's source is part of the pretraining cache key (``TRAINING_CODE``), so editing it
would retrain every cached model for no change in the weights."""

from __future__ import annotations

from collections.abc import Collection


def check_one_of(value: object, choices: Collection[str], option: str) -> None:
    """Raise ``ValueError`` naming ``option`` (as the user wrote it, e.g. ``--noise-split``)
    unless ``value`` is one of ``choices`` (a tuple, or a registry dict's keys)."""
    if value not in choices:
        raise ValueError(f"{option}: {value!r} is not one of {', '.join(choices)}")


def check_pretrain_gaps(value: float | str) -> None:
    """``--pretrain-gaps`` is ``"auto"`` or a probability in [0, 1] (``ValueError`` naming
    the option otherwise)."""
    if value == "auto":
        return
    if isinstance(value, str) or not 0.0 <= value <= 1.0:
        raise ValueError(f"--pretrain-gaps: must be 'auto' or in [0, 1], got {value!r}")
