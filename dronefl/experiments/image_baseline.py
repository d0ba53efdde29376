"""Does the paper's centralized baseline generalise from crop field to orchard? (SPEC §8)

``dronefl image-baseline`` records the scenario twice with the scripted pilot, in the crop field
(training; seed :data:`~dronefl.experiments.pretrain.PRETRAIN_SEED`, the closed loop's
pretraining recording) and in the orchard (seed ``PRETRAIN_SEED + 1``, never trained on),
renders every drone's frames through the JPEG uplink (:mod:`dronefl.perception.recorded_frames`)
and trains, on the first ``train_fraction`` of the crop-field steps of every drone pooled:

* ``image``: the paper's baseline, :class:`~dronefl.models.image.FrameTransformer` on frames
  and odometry, end to end;
* ``boxes``: the large box-based model (``centralized`` in Fig. 5, the cloud running YOLO on the
  same frames in the closed loop; here the projection detector's boxes).

Both are scored on the same cells (drone, target, step t -> position at t + 1): every box
window of the crop field's held-out last steps and of the whole orchard run, as the mean
squared distance (m^2) per drone, and over all drones by how far the target is from the
drone's nadir (the image centre; :data:`OFFSET_EDGES_M`). ``results.json`` holds both, the
image model's parameter count, training seconds per epoch, inference ms per sample and the
uplink's JPEG bytes; ``image_baseline.png`` compares them; ``image_model.npz`` holds the image
model's weights.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dronefl.config import Scenario
from dronefl.experiments.pretrain import PRETRAIN_SEED
from dronefl.experiments.simulate import simulate
from dronefl.io import atomic_savez, atomic_write_json
from dronefl.logs import load_run
from dronefl.models.image import (
    FrameTransformer,
    FrameWindows,
    ImageModelConfig,
    ImageTraining,
    chronological_rows,
    predict_windows,
    recorded_frame_windows,
    train_image_model,
)
from dronefl.models.model import build_model, count_parameters, predictor_config
from dronefl.models.train import TrainConfig, train_pooled
from dronefl.models.windows import (
    WindowSet,
    WindowSpec,
    build_windows,
    ground_truth_labels,
    split_windows,
)
from dronefl.perception.recorded_frames import render_run
from dronefl.report.fl_plots import plot_image_baseline
from dronefl.validation import check_positive

#: The two recordings: where the models learn and where they are deployed.
ENVIRONMENTS = ("crop_field", "orchard")
#: Bins (m) of the target's horizontal distance from the drone at t + 1, for the errors by
#: offset (the last bin is open).
OFFSET_EDGES_M = (0.0, 4.0, 8.0, 12.0, 20.0)


@dataclass(frozen=True)
class ImageBaselineConfig:
    """``scenario`` recorded for ``duration`` s in each environment; the models trained for
    ``epochs`` (Adam, ``lr``, ``batch_size``, ``seed``) on windows of ``past_steps`` L_p every
    ``stride`` steps of the first ``train_fraction`` of the crop field; frames of ``frame_px``
    pixels; results in ``out``."""

    scenario: Scenario
    out: Path
    duration: float = 600.0
    epochs: int = 30
    lr: float = 1e-3
    batch_size: int = 64
    seed: int = 0
    past_steps: int = 10
    stride: int = 2
    frame_px: int = 48
    train_fraction: float = 0.8
    progress: bool = True

    def __post_init__(self) -> None:
        for name in ("duration", "lr"):
            check_positive(getattr(self, name), f"--{name}")
        for name in ("epochs", "batch_size", "past_steps", "stride", "frame_px"):
            if getattr(self, name) < 1:
                raise ValueError(f"--{name.replace('_', '-')}: must be >= 1")
        if not 0 < self.train_fraction < 1:
            raise ValueError(f"--train-fraction: must be in (0, 1), got {self.train_fraction}")


@dataclass(frozen=True)
class Recording:
    """One recorded run with its box windows (train and held-out, per drone) and its frame
    windows (every step, per drone, in drone order: ``frame_sets``), and the uplink bytes."""

    boxes_train: list[WindowSet]
    boxes_test: list[WindowSet]
    frame_sets: dict[int, FrameWindows]
    jpeg_kb_per_frame: float


def record(config: ImageBaselineConfig, environment: str) -> Recording:
    """Record (if not yet), render and cut ``environment``'s run into windows."""
    seed = PRETRAIN_SEED + ENVIRONMENTS.index(environment)
    folder = Path(config.out) / environment
    if not (folder / "ground_truth.npz").is_file():
        simulate(
            config.scenario, environment=environment, duration=config.duration, seed=seed,
            out=folder, progress=config.progress, plot=False,
        )  # fmt: skip
    logs, truth = load_run(folder)
    rendered = render_run(folder, config.frame_px, progress=config.progress)
    every = WindowSpec(config.past_steps, 1, relative=True, stride=1, train_fraction=1.0)
    strided = dataclasses.replace(every, stride=config.stride, train_fraction=config.train_fraction)
    boxes_train, boxes_test = [], []
    for drone_id in rendered.drone_ids:
        log = logs[drone_id]
        labels = ground_truth_labels(log, truth)
        n_steps = len(log.t)
        if environment == "crop_field":  # trained on the first steps, scored on the rest
            split = int(n_steps * config.train_fraction)
            boxes_train.append(split_windows(log, labels, strided)[0])
            boxes_test.append(build_windows(log, labels, every, (split, n_steps)))
        else:  # never trained on: every step is scored
            boxes_test.append(build_windows(log, labels, every, (0, n_steps)))
    frame_sets = recorded_frame_windows(
        logs, truth, rendered.frames, rendered.drone_ids, config.past_steps
    )
    return Recording(boxes_train, boxes_test, frame_sets, float(rendered.jpeg_bytes.mean() / 1e3))


def _image_training_set(config: ImageBaselineConfig, recording: Recording) -> FrameWindows:
    """Every ``stride``-th frame window of the crop field's training steps with something
    visible to learn from, all drones."""
    parts = []
    for data in recording.frame_sets.values():
        train, _ = chronological_rows(data, config.stride, config.train_fraction)
        parts.append(data.subset(train))
    return FrameWindows.concat(parts)


def image_cell_errors(
    model: FrameTransformer,
    frame_sets: dict[int, FrameWindows],
    cells: list[WindowSet],
    target_ids: tuple[int, ...],
) -> dict[int, np.ndarray]:
    """Squared distance (m^2) of ``model``'s prediction of each cell (drone, target, t) of the
    box windows ``cells``, per drone."""
    slot = {t: j for j, t in enumerate(target_ids)}
    out = {}
    for windows in cells:
        if len(windows) == 0:
            continue
        drone = int(windows.drone_ids[0])
        data = frame_sets[drone]
        row_of = {int(t): r for r, t in enumerate(data.index[:, -1])}
        rows = np.array([row_of[int(t)] for t in windows.t_index])
        slots = np.array([slot[int(t)] for t in windows.target_ids])
        relative = predict_windows(model, data, rows)[np.arange(len(rows)), slots]
        truth = windows.labels[:, 0]  # relative to the same odometry position
        out[drone] = ((relative - truth) ** 2).sum(-1)
    return out


@torch.no_grad()
def box_cell_errors(model: torch.nn.Module, cells: list[WindowSet]) -> dict[int, np.ndarray]:
    """Squared distance (m^2) of the box model's prediction of each of its windows ``cells``,
    per drone."""
    model.eval()
    out = {}
    for windows in cells:
        if len(windows) == 0:
            continue
        predicted = model(torch.from_numpy(windows.features), torch.from_numpy(windows.altitude))
        error = predicted.numpy()[:, 0] - windows.labels[:, 0]
        out[int(windows.drone_ids[0])] = (error**2).sum(-1)
    return out


def cell_offsets(cells: list[WindowSet]) -> dict[int, np.ndarray]:
    """Each cell's target distance (m) at t + 1 from the drone's position at t, per drone."""
    return {int(w.drone_ids[0]): np.linalg.norm(w.labels[:, 0], axis=-1) for w in cells if len(w)}


def mse_by_offset(
    errors: dict[int, np.ndarray], offsets: dict[int, np.ndarray]
) -> dict[str, list[float]]:
    """Mean of ``errors`` (m^2) over all drones' cells in each bin of :data:`OFFSET_EDGES_M`
    (NaN: an empty bin) and the number of cells per bin."""
    error = np.concatenate([errors[d] for d in sorted(errors)])
    offset = np.concatenate([offsets[d] for d in sorted(errors)])
    bins = np.digitize(offset, OFFSET_EDGES_M[1:])
    mse = [float(error[bins == b].mean()) if (bins == b).any() else float("nan")
           for b in range(len(OFFSET_EDGES_M))]  # fmt: skip
    return {"mse": mse, "cells": [int((bins == b).sum()) for b in range(len(OFFSET_EDGES_M))]}


def _per_drone_mean(errors: dict[int, np.ndarray]) -> dict[int, float]:
    return {d: float(e.mean()) for d, e in errors.items()}


@torch.no_grad()
def _inference_ms(model: FrameTransformer, sample: FrameWindows) -> float:
    """Wall ms per window of one batched forward pass over ``sample`` (after a warm-up)."""
    model.eval()
    frames = torch.from_numpy(sample.frames[sample.index])
    odometry = torch.from_numpy(sample.odometry)
    model(frames, odometry)
    started = time.perf_counter()
    model(frames, odometry)
    return 1000 * (time.perf_counter() - started) / len(sample)


def run_image_baseline(config: ImageBaselineConfig) -> dict:
    """Record, render, train both models and score them (module doc); writes and returns
    ``results.json``."""
    crop, orchard = (record(config, env) for env in ENVIRONMENTS)
    target_ids = tuple(config.scenario.target_ids)
    image_config = ImageModelConfig(len(target_ids), config.past_steps, config.frame_px)
    torch.manual_seed(config.seed)
    image = FrameTransformer(image_config)
    training = _image_training_set(config, crop)
    image_stats = train_image_model(
        image, training, ImageTraining(config.epochs, config.lr, config.batch_size, config.seed)
    )
    large = build_model(predictor_config("large", config.past_steps, 1), seed=config.seed)
    started = time.perf_counter()
    box_stats = train_pooled(
        large,
        crop.boxes_train,
        TrainConfig(config.epochs, config.lr, config.batch_size, config.seed),
    )
    box_seconds = (time.perf_counter() - started) / config.epochs
    inference_ms = _inference_ms(image, training.subset(np.arange(min(64, len(training)))))
    places = {"crop_field_held_out": crop, "orchard": orchard}
    errors = {
        "image": {
            place: image_cell_errors(image, rec.frame_sets, rec.boxes_test, target_ids)
            for place, rec in places.items()
        },
        "boxes": {place: box_cell_errors(large, rec.boxes_test) for place, rec in places.items()},
    }
    scores = {m: {p: _per_drone_mean(e) for p, e in by.items()} for m, by in errors.items()}
    offsets = {place: cell_offsets(rec.boxes_test) for place, rec in places.items()}
    by_offset = {
        "edges_m": list(OFFSET_EDGES_M),
        **{m: {p: mse_by_offset(e, offsets[p]) for p, e in by.items()} for m, by in errors.items()},
    }
    results = {
        "scenario": config.scenario.name,
        "settings": {k: str(v) if isinstance(v, Path) else v
                     for k, v in dataclasses.asdict(config).items() if k != "scenario"},
        "model_input": "frames",
        "image_model": {
            "parameters": count_parameters(image),
            "config": dataclasses.asdict(image_config),
            "train_seconds_per_epoch": image_stats.seconds_per_epoch,
            "inference_ms_per_sample": inference_ms,
            "train_loss": list(image_stats.loss),
            "training_windows": len(training),
            "threads": torch.get_num_threads(),
        },
        "box_model": {
            "parameters": count_parameters(large),
            "train_seconds_per_epoch": box_seconds,
            "final_train_loss": box_stats.loss,
        },
        "jpeg_kb_per_frame": {"crop_field": crop.jpeg_kb_per_frame,
                              "orchard": orchard.jpeg_kb_per_frame},
        "mse": scores,
        "mse_by_offset": by_offset,
    }  # fmt: skip
    out = Path(config.out)
    atomic_savez(out / "image_model.npz", **{k: v.numpy() for k, v in image.state_dict().items()})
    atomic_write_json(out / "results.json", results)
    saved = json.loads((out / "results.json").read_text())
    plot_image_baseline(saved, out / "image_baseline.png")
    return saved
