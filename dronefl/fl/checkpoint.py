"""Atomic per-round checkpoints of the global model, and resuming from them.

After every global round the server writes ``checkpoint.npz`` (the global weights, the round
and the method) and ``history.json`` (one entry per finished round), each atomically, so a
killed run loses at most the round in progress. ``--resume`` continues at the next round.
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


class CheckpointError(ValueError):
    """A checkpoint or history file is missing, corrupt or from another run."""


@dataclass(frozen=True)
class Checkpoint:
    """The global model ``state`` after global round ``server_round`` of ``method``, with the
    ``history`` of every round up to it."""

    method: str
    server_round: int
    state: dict[str, torch.Tensor]
    history: list[RoundRecord]


def save_checkpoint(path: Path, history_path: Path, checkpoint: Checkpoint) -> None:
    """Write the weights, then the history (each atomically)."""
    arrays = {_PREFIX + k: v.detach().cpu().numpy() for k, v in checkpoint.state.items()}
    atomic_savez(
        path,
        format=np.array(CHECKPOINT_FORMAT),
        method=np.array(checkpoint.method),
        server_round=np.array(checkpoint.server_round),
        **arrays,
    )
    atomic_write_json(history_path, [r.to_json() for r in checkpoint.history])


def load_checkpoint(path: Path, history_path: Path, method: str) -> Checkpoint:
    """Read a checkpoint of ``method``; raises :class:`CheckpointError` on any problem."""
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
    except CheckpointError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        raise CheckpointError(
            f"{path}: truncated or corrupt checkpoint ({type(exc).__name__})"
        ) from None
    if saved_method != method:
        raise CheckpointError(f"{path}: checkpoint of method {saved_method!r}, not {method!r}")
    if not all(bool(torch.isfinite(v).all()) for v in state.values()):
        raise CheckpointError(f"{path}: checkpoint holds non-finite weights")
    try:
        history = json.loads(history_path.read_text())
    except (OSError, json.JSONDecodeError):
        raise CheckpointError(f"{history_path}: missing or corrupt round history") from None
    if not isinstance(history, list):
        raise CheckpointError(f"{history_path}: round history must be a list")
    try:
        records = [RoundRecord.from_json(entry) for entry in history]
    except SettingsError as exc:
        raise CheckpointError(f"{history_path}: {exc}") from None
    records = [r for r in records if r.server_round <= server_round]
    return Checkpoint(saved_method, server_round, state, records)
