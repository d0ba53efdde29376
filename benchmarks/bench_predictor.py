"""Predictor latency on this machine, single-threaded (issue 3 goals in brackets):

* inference for one drone step with 6 targets [<= 0.3 ms], through
  :class:`dronefl.models.predictor.TrajectoryPredictor` (feature building included) with the
  eager, TorchScript and ONNX Runtime runtimes, and the model call alone;
* one local training epoch of 500 windows x 6 targets [<= 0.3 s] (batch 128, Adam, MSE);

each beside the same architecture built from stock eager ``nn.TransformerEncoderLayer`` /
``nn.TransformerDecoder`` (same embedding, positions, AdaIN and head), measured in the same run.
The windows are real: Case 3's highest drone (6 targets) recorded for 600 s.

Run: ``.venv/bin/python benchmarks/bench_predictor.py [--repeats 5]``
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

from dronefl.config import load_scenario
from dronefl.experiments.simulate import simulate
from dronefl.logs import load_run
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
    position_scale,
)


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
        self.output_scale = position_scale(config.relative)  # m per head unit

    def forward(self, features: torch.Tensor, altitude: torch.Tensor) -> torch.Tensor:
        x = self.embed(features) + self.pe_past  # (B, L_p, d)
        for layer, adain in zip(self.encoder, self.adain, strict=True):
            x = layer(x)
            x = x + adain(x, altitude)
        y = (self.queries + self.pe_future).expand(features.shape[0], -1, -1)  # (B, L_f, d)
        return self.head(self.decoder(y, x)) * self.output_scale  # (B, L_f, 2) m


def record_windows(folder: Path) -> tuple[WindowSet, dict]:
    """3,000 windows (500 per target) and one drone step of Case 3's drone 1."""
    simulate(load_scenario("case3"), duration=600.0, seed=0, out=folder, progress=False,
             plot=False)  # fmt: skip
    logs, truth = load_run(folder)
    log = logs[1]
    windows = build_windows(log, ground_truth_labels(log, truth), WindowSpec())
    per_target = [np.flatnonzero(windows.target_ids == j)[:500] for j in log.assigned_ids]
    picked = np.concatenate(per_target)
    sample = WindowSet(*(getattr(windows, k)[picked] for k in WindowSet.__dataclass_fields__))
    t = 1000
    step = {
        "odometry": log.odometry[t - 9 : t + 1],
        "boxes": log.boxes[t - 9 : t + 1][:, log.assigned],
        "detected": log.detected[t - 9 : t + 1][:, log.assigned],
    }
    return sample, step


def best_of(fn, repeats: int, number: int) -> float:
    """Median over ``repeats`` of the mean seconds per call over ``number`` calls."""
    for _ in range(min(number, 20)):
        fn()
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        for _ in range(number):
            fn()
        times.append((time.perf_counter() - started) / number)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)
    config = predictor_config("dronefl")
    ours, stock = build_model(config), StockPredictor(config)
    with tempfile.TemporaryDirectory() as tmp:
        data, step = record_windows(Path(tmp))
    print(f"torch {torch.__version__}, 1 thread; model: {count_parameters(ours)} parameters "
          f"(stock build: {count_parameters(stock)})")  # fmt: skip
    print(f"data: {len(data)} windows of Case 3 drone 1 (6 targets), one step = 6 targets\n")

    print("inference, one drone step with 6 targets [goal <= 0.3 ms]")
    x = torch.from_numpy(
        np.stack([data.features[data.target_ids == j][0] for j in range(1, 7)])
    )  # (6, L_p, F)
    h = torch.full((6,), 60.0)
    ours.eval()
    stock.eval()
    with torch.no_grad():
        stock_s = best_of(lambda: stock(x, h), args.repeats, 500)
        rows = [("stock nn.Transformer* eager, model call", stock_s)]
        rows.append(("ours eager, model call", best_of(lambda: ours(x, h), args.repeats, 500)))
    for runtime in ("torch", "torchscript", "onnx"):
        predictor = TrajectoryPredictor(ours, runtime=runtime)
        rows.append(
            (f"ours {runtime}, predict() incl. features",
             best_of(lambda p=predictor: p.predict(**step), args.repeats, 500))
        )  # fmt: skip
    for name, seconds in rows:
        print(f"  {name:44s} {seconds * 1e3:7.3f} ms   stock/this {stock_s / seconds:5.2f}x")

    print("\ntraining, one epoch of 500 windows x 6 targets, batch 128 [goal <= 0.3 s]")
    epochs = 3
    results = {}
    for name, model in (("stock nn.Transformer* eager", stock), ("ours", ours)):
        per_epoch = [
            train_local(model, data, TrainConfig(epochs=epochs, seed=k)).seconds_per_epoch
            for k in range(args.repeats)
        ]
        results[name] = statistics.median(per_epoch)
    stock_epoch = results["stock nn.Transformer* eager"]
    for name, seconds in results.items():
        print(f"  {name:44s} {seconds:7.3f} s    stock/this {stock_epoch / seconds:5.2f}x")


if __name__ == "__main__":
    main()
