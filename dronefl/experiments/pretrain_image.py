"""The image model's crop-field pretraining (the ``image`` kind of
:mod:`dronefl.experiments.pretrain`).

The crop-field recording's frames are rendered through the JPEG uplink once
(:func:`~dronefl.perception.recorded_frames.render_run`, cached beside the recording); the
image model trains on every drone's first :data:`IMAGE_TRAIN_FRACTION` of the steps as
:data:`IMAGE_PRETRAINING` says (``dronefl image-baseline``'s setting: 30 epochs, Adam 1e-3,
batches of 64, seed 0), labelled by the truth where the drone detected its assigned target, and
is scored on the rest. Its cache key (:meth:`PretrainSpec.image_dir
<dronefl.experiments.pretrain.PretrainSpec.image_dir>`) holds this module's code.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from dronefl.io import atomic_savez, atomic_write_json
from dronefl.logs import load_run
from dronefl.models.image import (
    FrameTransformer,
    FrameWindows,
    ImageTraining,
    chronological_rows,
    evaluate_image_model,
    recorded_frame_windows,
    train_image_model,
)
from dronefl.models.model import count_parameters
from dronefl.perception.recorded_frames import render_run
from dronefl.progress import progress_bar

if TYPE_CHECKING:
    from dronefl.experiments.pretrain import PretrainSpec

#: The image model's crop-field training and the share of the recording it trains on.
IMAGE_PRETRAINING = ImageTraining()
IMAGE_TRAIN_FRACTION = 0.8


def pretrain_image(spec: PretrainSpec, folder: Path, progress: bool) -> dict[str, torch.Tensor]:
    """Render the recorded crop field's frames (cached), train the image model, score it on
    the held-out steps; write ``pretrain.json`` (losses, held-out masked MSE per drone in m^2,
    parameters, s per epoch) and then the weights, ``image_model.npz``. Weights already there
    are returned as they are. The recording must exist (:func:`~dronefl.experiments.pretrain.
    pretrain` records it)."""
    path = spec.model_path(folder)
    if path.is_file():
        return load_image_state(path)
    data = spec.data_dir(folder)
    logs, truth = load_run(data)
    config = spec.image_model
    rendered = render_run(data, config.frame_px, progress=progress)
    sets = recorded_frame_windows(logs, truth, rendered.frames, rendered.drone_ids, spec.past_steps)
    train, held_out = [], []
    for windows in sets.values():
        rows, rest = chronological_rows(windows, spec.stride, IMAGE_TRAIN_FRACTION)
        train.append(windows.subset(rows))
        held_out.append(windows.subset(rest))
    torch.manual_seed(IMAGE_PRETRAINING.seed)
    model = FrameTransformer(config)
    name = f"pretrain {spec.scenario.name} image"
    with progress_bar(name, IMAGE_PRETRAINING.epochs, progress) as advance:
        stats = train_image_model(
            model, FrameWindows.concat(train), IMAGE_PRETRAINING, on_epoch=lambda _: advance(1)
        )
    report = {
        "model_input": "frames",
        "parameters": count_parameters(model),
        "config": dataclasses.asdict(config),
        "training": dataclasses.asdict(IMAGE_PRETRAINING),
        "train_loss": list(stats.loss),
        "train_seconds_per_epoch": stats.seconds_per_epoch,
        "training_windows": sum(len(w) for w in train),
        "held_out_mse": evaluate_image_model(model, FrameWindows.concat(held_out)),
        "jpeg_kb_per_frame": float(rendered.jpeg_bytes.mean() / 1e3),
    }
    atomic_write_json(path.parent / "pretrain.json", report)
    atomic_savez(path, **{k: v.numpy() for k, v in model.state_dict().items()})
    return model.state_dict()


def load_image_state(path: Path) -> dict[str, torch.Tensor]:
    """The image model's weights saved by :func:`pretrain_image`."""
    with np.load(path) as data:
        return {k: torch.from_numpy(data[k].copy()) for k in data.files}
