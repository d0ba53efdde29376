"""Predictor latency on one thread: inference per drone step and local training per epoch.

The data are real: Case 3 recorded under the scripted pilot in the crop field, seen by drone 1
(60 m, all 6 targets), cut into the closed loop's windows (L_p = 10, L_f = 1). The reference is
the same architecture built from PyTorch's stock eager ``nn.TransformerEncoderLayer`` /
``nn.TransformerDecoder`` (same embedding, positions, AdaIN and head), timed in the same run.
The paper's centralized baseline, the image model, is timed on the same number of windows and
targets (:func:`bench_image`), on random pixels: its cost does not depend on what they show.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import ParamSpec, TypeVar

import numpy as np
import torch
from torch import nn

from dronefl.bench.energy import EnergyMeter
from dronefl.bench.results import Benchmarks
from dronefl.bench.timing import latency, time_interleaved, with_reference
from dronefl.config import Scenario
from dronefl.experiments.simulate import simulate
from dronefl.logs import load_run
from dronefl.models.image import (
    FrameTransformer,
    FrameWindows,
    ImageModelConfig,
    ImageTraining,
    train_image_model,
)
from dronefl.models.model import (
    AltitudeAdaIN,
    PredictorConfig,
    build_model,
    count_parameters,
    predictor_config,
    sinusoidal_positions,
)
from dronefl.models.predictor import TrajectoryPredictor
from dronefl.models.train import TrainConfig, train_local
from dronefl.models.windows import (
    WindowSet,
    WindowSpec,
    build_windows,
    ground_truth_labels,
)

P = ParamSpec("P")
R = TypeVar("R")
#: The closed loop's windows: 10 past steps, 1 future step.
PAST_STEPS, FUTURE_STEPS = 10, 1


class StockPredictor(nn.Module):
    """The DroneFL architecture from PyTorch's stock transformer layers (the reference)."""

    def __init__(self, config: PredictorConfig) -> None:
        super().__init__()
        self.config = config
        d = config.d_model
        self.embed = nn.Linear(config.input_dim, d)
        self.queries = nn.Parameter(0.02 * torch.randn(config.future_steps, d))
        pe = sinusoidal_positions(torch.arange(config.past_steps + config.future_steps), d)
        self.register_buffer("pe_past", pe[: config.past_steps].clone(), persistent=False)
        self.register_buffer("pe_future", pe[config.past_steps :].clone(), persistent=False)
        layer = dict(d_model=d, nhead=config.n_heads, dim_feedforward=config.d_ff,
                     dropout=config.dropout, batch_first=True)  # fmt: skip
        self.encoder = nn.ModuleList(
            nn.TransformerEncoderLayer(**layer) for _ in range(config.n_encoder_layers)
        )
        self.adain = nn.ModuleList(AltitudeAdaIN(d) for _ in range(config.n_encoder_layers))
        self.decoder = nn.TransformerDecoder(
            nn.TransformerDecoderLayer(**layer), num_layers=config.n_decoder_layers
        )
        self.head = nn.Linear(d, 2)
        self.output_scale = config.frame.scale_m  # m per head unit

    def forward(self, features: torch.Tensor, altitude: torch.Tensor) -> torch.Tensor:
        """Positions ``(B, L_f, 2)`` m from ``features`` ``(B, L_p, F)`` and ``altitude``
        ``(B,)`` m, like :class:`~dronefl.models.model.TrajectoryTransformer`."""
        x = self.embed(features) + self.pe_past  # (B, L_p, d)
        for layer, adain in zip(self.encoder, self.adain, strict=True):
            x = layer(x)
            x = x + adain(x, altitude)
        y = (self.queries + self.pe_future).expand(features.shape[0], -1, -1)  # (B, L_f, d)
        return self.head(self.decoder(y, x)) * self.output_scale  # (B, L_f, 2) m


def record_windows(
    scenario: Scenario, folder: Path, duration: float, per_target: int
) -> tuple[WindowSet, dict]:
    """Record ``duration`` s of ``scenario`` into ``folder``; return up to ``per_target``
    windows of each of drone 1's targets and one drone step (the ``predict`` arguments of the
    step whose window holds the most detected targets)."""
    simulate(scenario, duration=duration, seed=0, out=folder, progress=False,
             plot=False)  # fmt: skip
    logs, truth = load_run(folder)
    log = logs[1]
    spec = WindowSpec(PAST_STEPS, FUTURE_STEPS)
    windows = build_windows(log, ground_truth_labels(log, truth), spec)
    picked = np.concatenate(
        [np.flatnonzero(windows.target_ids == j)[:per_target] for j in log.assigned_ids]
    )
    sample = WindowSet(*(getattr(windows, k)[picked] for k in WindowSet.__dataclass_fields__))
    detected = log.detected[:, log.assigned]  # (T, 6)
    ends = range(PAST_STEPS, len(log.t) + 1)  # window = steps [end - L_p, end)
    seen = [detected[end - PAST_STEPS : end].any(axis=0).sum() for end in ends]
    end = ends[int(np.argmax(seen))]
    window = slice(end - PAST_STEPS, end)
    step = {
        "odometry": log.odometry[window],
        "boxes": log.boxes[window][:, log.assigned],
        "detected": detected[window],
    }
    return sample, step


def _one_torch_thread(fn: Callable[P, R]) -> Callable[P, R]:
    """Run ``fn`` with torch on one intra-op thread (what the figures state), then restore."""

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        previous = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            return fn(*args, **kwargs)
        finally:
            torch.set_num_threads(previous)

    return wrapper


@_one_torch_thread
def bench_inference(
    step: dict, calls: int, rounds: int, measure_energy: EnergyMeter | None = None
) -> Benchmarks:
    """Per drone step, features included, 1 thread, ms:

    * ``predictor_inference``: our model on ONNX Runtime (what the drones run), against the stock
      eager build; ``other_runtimes`` holds our model eager and TorchScript;
    * ``centralized_inference``: the centralized baseline's ``large`` model on ONNX Runtime.

    ``step`` holds :meth:`TrajectoryPredictor.predict`'s arguments; each function is called
    ``rounds`` x ``calls`` times (interleaved). With ``measure_energy`` the ONNX predictor's
    energy per call is measured too (``energy_reading``).
    """
    torch.manual_seed(0)
    config = predictor_config("dronefl", PAST_STEPS, FUTURE_STEPS)
    ours, stock = build_model(config), StockPredictor(config)
    large = build_model(predictor_config("large", PAST_STEPS, FUTURE_STEPS))
    # StockPredictor has the interface TrajectoryPredictor uses: config, eval(), __call__.
    predictors = {
        "onnx": TrajectoryPredictor(ours, runtime="onnx", threads=1),
        "torchscript": TrajectoryPredictor(ours, runtime="torchscript"),
        "torch": TrajectoryPredictor(ours, runtime="torch"),
        "stock": TrajectoryPredictor(stock, runtime="torch"),  # type: ignore[arg-type]
        "large": TrajectoryPredictor(large, runtime="onnx", threads=1),
    }
    n_targets = int(step["boxes"].shape[1])
    with torch.inference_mode():
        seconds = time_interleaved(
            {name: (lambda p=p: p.predict(**step)) for name, p in predictors.items()},
            calls,
            rounds,
        )
    threads = torch.get_num_threads()
    what = f"one drone step, {n_targets} targets, features included"
    reference = latency("stock eager nn.Transformer* build", seconds["stock"], "ms", threads)
    ours_figure = replace(
        with_reference(latency(f"{what}; ONNX Runtime", seconds["onnx"], "ms", 1), reference),
        targets=n_targets,
        parameters=count_parameters(ours),
        reference_parameters=count_parameters(stock),
        other_runtimes={
            name: latency(f"{what}; our model, {name}", seconds[name], "ms", threads)
            for name in ("torch", "torchscript")
        },
    )
    centralized = replace(
        latency(f"{what}; centralized large model, ONNX Runtime", seconds["large"], "ms", 1),
        targets=n_targets,
        parameters=count_parameters(large),
    )
    if measure_energy is not None:
        onnx = predictors["onnx"]
        reading = measure_energy(lambda: onnx.predict(**step), rounds * calls)
        ours_figure = replace(ours_figure, energy_reading=reading)
    return Benchmarks(predictor_inference=ours_figure, centralized_inference=centralized)


@_one_torch_thread
def bench_training(
    data: WindowSet, rounds: int, measure_energy: EnergyMeter | None = None
) -> Benchmarks:
    """One local epoch over ``data`` (Adam, batch 128, MSE), s, 1 thread:

    * ``training_epoch``: our model against the stock build;
    * ``centralized_training_epoch``: the ``large`` model on the same windows.

    ``rounds`` epochs of each, taking turns, after one warm-up epoch each. With
    ``measure_energy`` our model's energy per epoch is measured too (``energy_reading``).
    """
    torch.manual_seed(0)
    config = predictor_config("dronefl", PAST_STEPS, FUTURE_STEPS)
    models = {
        "ours": build_model(config),
        "stock": StockPredictor(config),
        "large": build_model(predictor_config("large", PAST_STEPS, FUTURE_STEPS)),
    }

    def epoch(model: nn.Module, seed: int) -> float:
        return train_local(model, data, TrainConfig(epochs=1, seed=seed)).seconds_per_epoch

    for model in models.values():
        epoch(model, seed=0)
    seconds = {name: np.empty(rounds) for name in models}
    for k in range(rounds):
        for name, model in models.items():
            seconds[name][k] = epoch(model, seed=k + 1)
    threads = torch.get_num_threads()
    what = f"one epoch of {len(data)} windows, batch 128"
    reference = latency("stock eager nn.Transformer* build", seconds["stock"], "s", threads)
    ours = replace(
        with_reference(latency(f"{what}; our model", seconds["ours"], "s", threads), reference),
        windows=len(data),
    )
    centralized = replace(
        latency(f"{what}; centralized large model", seconds["large"], "s", threads),
        windows=len(data),
    )
    if measure_energy is not None:
        reading = measure_energy(lambda: epoch(models["ours"], seed=0), rounds)
        ours = replace(ours, energy_reading=reading)
    return Benchmarks(training_epoch=ours, centralized_training_epoch=centralized)


@_one_torch_thread
def bench_image(n_windows: int, n_targets: int, calls: int, rounds: int) -> Benchmarks:
    """The paper's centralized baseline, the image model (``n_targets`` slots, L_p = 10
    frames of 48 px and odometry), eager torch, 1 thread:

    * ``image_inference``: one drone step (one window), ms, ``rounds`` x ``calls`` calls;
    * ``image_training_epoch``: one epoch over ``n_windows`` windows (Adam, batch 64,
      masked MSE), s, ``rounds`` epochs after a warm-up batch.

    The frames are random pixels (rendering thousands of frames would dominate the benchmark;
    the model's cost does not depend on the pixels' values)."""
    torch.manual_seed(0)
    config = ImageModelConfig(n_targets, PAST_STEPS)
    model = FrameTransformer(config).eval()
    rng = np.random.default_rng(0)
    px = config.frame_px
    frames = torch.from_numpy(rng.integers(0, 256, (1, PAST_STEPS, px, px, 3), dtype=np.uint8))
    odometry = torch.from_numpy(rng.random((1, PAST_STEPS, 3), dtype=np.float32))
    with torch.inference_mode():
        step = time_interleaved({"image": lambda: model(frames, odometry)}, calls, rounds)
    data = FrameWindows(
        frames=rng.integers(0, 256, (n_windows + PAST_STEPS, px, px, 3), dtype=np.uint8),
        index=np.arange(n_windows)[:, None] + np.arange(PAST_STEPS)[None, :],
        odometry=rng.random((n_windows, PAST_STEPS, 3), dtype=np.float32),
        label=rng.normal(size=(n_windows, n_targets, 2)).astype(np.float32),
        mask=np.ones((n_windows, n_targets), dtype=bool),
        drone=np.ones(n_windows, dtype=np.int64),
    )
    training = ImageTraining(epochs=1)
    train_image_model(model, data.subset(np.arange(min(64, n_windows))), training)  # warm-up
    epochs = np.array(
        [train_image_model(model, data, training).seconds_per_epoch for _ in range(rounds)]
    )
    threads = torch.get_num_threads()
    parameters = count_parameters(model)
    what = f"{n_targets} targets; centralized image model (10 frames of {px} px + odometry)"
    return Benchmarks(
        image_inference=replace(
            latency(f"one drone step, {what}, eager torch", step["image"], "ms", threads),
            targets=n_targets,
            parameters=parameters,
        ),
        image_training_epoch=replace(
            latency(f"one epoch of {n_windows} windows, batch 64, {what}", epochs, "s", threads),
            windows=n_windows,
            parameters=parameters,
        ),
    )
