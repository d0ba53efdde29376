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

import numpy as np
import torch

from dronefl.io import atomic_savez, atomic_write_json
from dronefl.logs import load_run
from dronefl.models.image import (
    FrameTransformer,
    FrameWindows,
    ImageModelConfig,
    ImageTraining,
    chronological_rows,
    evaluate_image_model,
    recorded_frame_windows,
    train_image_model,
)
from dronefl.models.model import count_parameters
from dronefl.perception.recorded_frames import render_run
from dronefl.progress import progress_bar

#: The image model's crop-field training and the share of the recording it trains on.
IMAGE_PRETRAINING = ImageTraining()
IMAGE_TRAIN_FRACTION = 0.8


def pretrain_image(
    data: Path, path: Path, config: ImageModelConfig, stride: int, name: str, progress: bool
) -> dict[str, torch.Tensor]:
    """Render the frames of the crop field recorded in ``data`` (cached), train the image
    model ``config`` on windows every ``stride`` steps, score it on the held-out steps; write
    ``pretrain.json`` (losses, held-out masked MSE per drone in m^2, parameters, s per epoch)
    beside ``path`` and then the weights, ``path``. Weights already there are returned as they
    are; ``name`` labels the progress bar."""
    if path.is_file():
        return load_image_state(path)
    logs, truth = load_run(data)
    rendered = render_run(data, config.frame_px, progress=progress)
    sets = recorded_frame_windows(
        logs, truth, rendered.frames, rendered.drone_ids, config.past_steps
    )
    train, held_out = [], []
    for windows in sets.values():
        rows, rest = chronological_rows(windows, stride, IMAGE_TRAIN_FRACTION)
        train.append(windows.subset(rows))
        held_out.append(windows.subset(rest))
    torch.manual_seed(IMAGE_PRETRAINING.seed)
    model = FrameTransformer(config)
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
    with np.load(path, allow_pickle=False) as data:
        return {k: torch.from_numpy(data[k].copy()) for k in data.files}
