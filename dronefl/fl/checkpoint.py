"""Atomic per-round checkpoints of the global model, and resuming from them.

After every global round the server writes ``history.json`` (one entry per finished round) and
then ``checkpoint.npz`` (the global weights, the round, the method and, with SCAFFOLD, the
cloud's control variate), each atomically and fsynced. In that order a kill between the two
leaves a history one round ahead of the checkpoint, whose extra entry is dropped on resume (the
round is played again, bit for bit);
never a checkpoint whose history lacks a round. So a killed run loses at most the round in
progress, and ``--resume`` continues at the next round.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dronefl.fl.records import RoundRecord, SettingsError
from dronefl.io import atomic_savez, atomic_write_json

CHECKPOINT_FORMAT = "dronefl.fl_checkpoint"
_PREFIX = "w:"
_CONTROL_PREFIX = "c:"


class CheckpointError(ValueError):
    """A checkpoint or history file is missing, corrupt or from another run."""


@dataclass(frozen=True)
class Checkpoint:
    """The global model ``state`` after global round ``server_round`` of ``method``, with the
    ``history`` of every round up to it and, with SCAFFOLD, the cloud's ``control`` variate."""

    method: str
    server_round: int
    state: dict[str, torch.Tensor]
    history: list[RoundRecord]
    control: dict[str, torch.Tensor] | None = None


def save_checkpoint(path: Path, history_path: Path, checkpoint: Checkpoint) -> None:
    """Write the history, then the weights (each atomically)."""
    atomic_write_json(history_path, [r.to_json() for r in checkpoint.history])
    arrays = {_PREFIX + k: v.detach().cpu().numpy() for k, v in checkpoint.state.items()}
    for k, v in (checkpoint.control or {}).items():
        arrays[_CONTROL_PREFIX + k] = v.detach().cpu().numpy()
    atomic_savez(
        path,
        format=np.array(CHECKPOINT_FORMAT),
        method=np.array(checkpoint.method),
        server_round=np.array(checkpoint.server_round),
        **arrays,
    )


def load_checkpoint(
    path: Path,
    history_path: Path,
    method: str,
    like: dict[str, torch.Tensor] | None = None,
) -> Checkpoint:
    """Read a checkpoint of ``method`` (whose tensors must have the names and shapes of
    ``like``, when given) and its history; raises :class:`CheckpointError` naming the file on
    any problem."""
    path, history_path = Path(path), Path(history_path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint to resume from")
    try:
        with np.load(path, allow_pickle=False) as npz:
            if "format" not in npz.files or str(npz["format"]) != CHECKPOINT_FORMAT:
                raise CheckpointError(f"{path}: not a DroneFL FL checkpoint")
            saved_method, server_round = str(npz["method"]), int(npz["server_round"])
            state = {
                k[len(_PREFIX) :]: torch.from_numpy(npz[k].copy())
                for k in npz.files
                if k.startswith(_PREFIX)
            }
            control = {
                k[len(_CONTROL_PREFIX) :]: torch.from_numpy(npz[k].copy())
                for k in npz.files
                if k.startswith(_CONTROL_PREFIX)
            }
    except CheckpointError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError, TypeError) as exc:
        raise CheckpointError(
            f"{path}: truncated or corrupt checkpoint ({type(exc).__name__})"
        ) from None
    if saved_method != method:
        raise CheckpointError(f"{path}: checkpoint of method {saved_method!r}, not {method!r}")
    if server_round < 1:
        raise CheckpointError(f"{path}: round {server_round} is not a finished round")
    if not state or not all(v.is_floating_point() for v in state.values()):
        raise CheckpointError(f"{path}: checkpoint holds no floating-point weights")
    if not all(bool(torch.isfinite(v).all()) for v in [*state.values(), *control.values()]):
        raise CheckpointError(f"{path}: checkpoint holds non-finite weights")
    if like is not None:
        _check_like(path, state, like)
        if control:
            _check_like(path, control, like)
    history = load_history(history_path, server_round)
    return Checkpoint(saved_method, server_round, state, history, control or None)


def _check_like(path: Path, state: dict[str, torch.Tensor], like: dict[str, torch.Tensor]) -> None:
    if set(state) != set(like):
        missing, extra = sorted(set(like) - set(state)), sorted(set(state) - set(like))
        raise CheckpointError(
            f"{path}: weights of another model (missing {missing[:3]}, unexpected {extra[:3]})"
        )
    for name, tensor in like.items():
        if tuple(state[name].shape) != tuple(tensor.shape):
            raise CheckpointError(
                f"{path}: '{name}' has shape {tuple(state[name].shape)}, "
                f"expected {tuple(tensor.shape)}"
            )


def load_history(history_path: Path, server_round: int) -> list[RoundRecord]:
    """The entries of rounds ``1..server_round`` of a round history (entries of later rounds,
    written just before a kill, are dropped); raises :class:`CheckpointError` naming the file
    when it is missing, corrupt or lacks one of those rounds. An empty history is allowed (a
    checkpoint written outside FL rounds, e.g. a model trained elsewhere)."""
    history_path = Path(history_path)
    try:
        history = json.loads(history_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        raise CheckpointError(f"{history_path}: missing or corrupt round history") from None
    if not isinstance(history, list):
        raise CheckpointError(f"{history_path}: round history must be a list of round entries")
    try:
        records = [RoundRecord.from_json(entry) for entry in history]
    except SettingsError as exc:
        raise CheckpointError(f"{history_path}: {exc}") from None
    kept = [r for r in records if r.server_round <= server_round]
    if kept and [r.server_round for r in kept] != list(range(1, server_round + 1)):
        raise CheckpointError(
            f"{history_path}: round history does not hold rounds 1..{server_round} in order"
        )
    return kept
