"""Pretraining for the closed loop: models learned offline in the crop field (SPEC §8).

For a case, :func:`pretrain` records ``duration`` s of the crop field under the scripted pilot
(seed :data:`PRETRAIN_SEED`, never used by an evaluation episode) and trains, with ground-truth
labels and windows L_p = 10 -> L_f = 1:

* ``dronefl``: the position-invariant AdaIN model by federated learning (FedAvg on Flower);
  the fixed-distributed and DroneFL episodes both start from it;
* ``centralized``: the large model on the pooled windows of every drone, in the cloud.

Results are cached as ``<folder>/case<N>/<kind>/checkpoint.npz`` and reused by every episode.
"""

from __future__ import annotations

from pathlib import Path

import torch

from dronefl.config import load_scenario
from dronefl.experiments.fl_offline import run_centralized
from dronefl.experiments.simulate import simulate
from dronefl.fl.checkpoint import load_checkpoint
from dronefl.fl.records import FlSettings
from dronefl.fl.simulation import run_federated
from dronefl.progress import progress_bar

PRETRAIN_SEED = 1000
KINDS = ("dronefl", "centralized")


def pretrain_settings(case: int, kind: str, folder: Path, rounds: int = 20) -> FlSettings:
    """Where and how ``kind`` is pretrained for ``case``."""
    if kind not in KINDS:
        raise ValueError(f"pretrained model kind must be one of {KINDS}, got {kind!r}")
    root = Path(folder) / f"case{case}"
    return FlSettings(
        run_dir=str(root / "data"),
        out_dir=str(root / kind),
        method=kind,
        rounds=rounds,
        past_steps=10,
        future_steps=1,
        stride=2,
        seed=0,
    )


def pretrain(
    case: int,
    kind: str,
    folder: Path,
    rounds: int = 20,
    duration: float = 600.0,
    progress: bool = True,
) -> dict[str, torch.Tensor]:
    """Record the crop field (if not yet recorded) and train ``kind``; returns its weights."""
    settings = pretrain_settings(case, kind, folder, rounds)
    data = Path(settings.run_dir)
    if not (data / "ground_truth.npz").is_file():
        simulate(
            load_scenario(f"case{case}"),
            environment="crop_field",
            duration=duration,
            seed=PRETRAIN_SEED,
            out=data,
            progress=progress,
            plot=False,
        )
    with progress_bar(f"pretrain case{case} {kind}", rounds, progress) as advance:
        train = run_federated if kind == "dronefl" else run_centralized
        train(settings, on_round=lambda _: advance(1))
    return load_checkpoint(settings.checkpoint_path, settings.history_path, kind).state


def pretrained_state(
    case: int, kind: str, folder: Path, progress: bool = True
) -> dict[str, torch.Tensor]:
    """The cached pretrained weights of ``kind`` for ``case``, pretraining them if missing."""
    settings = pretrain_settings(case, kind, folder)
    if settings.checkpoint_path.is_file():
        checkpoint = load_checkpoint(settings.checkpoint_path, settings.history_path, kind)
        if checkpoint.server_round >= settings.rounds:
            return checkpoint.state
    return pretrain(case, kind, folder, progress=progress)
