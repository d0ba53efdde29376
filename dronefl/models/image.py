"""The centralized baseline's image model: frames and odometry in, target positions out (SPEC §8).

The paper's centralized baseline sends each drone's raw camera frames and odometry to the cloud,
which trains one large model on them end to end: no detector, no boxes. Reading order:
:class:`ImageModelConfig`, :class:`FrameTransformer` (whose ``forward`` reads top to bottom),
the windows it learns from (:class:`FrameWindows`, :func:`frame_windows`) and its training
(:func:`train_image_model`, :func:`evaluate_image_model`)::

    frames (B, L_p, P, P, 3) uint8 --/255, CNN (stride-2 convs, ReLU)--> (B, L_p, d)
    odometry (B, L_p, 3) [z / 50 m, vx, vy] --linear--> (B, L_p, d)     (added) + positions
      -> transformer encoder x n_layers -> last step (B, d)
      -> linear head (N slots x 2) x z_t / 50 m                          (B, N, 2) m

The image model trains with its own setting (:class:`ImageTraining`: Adam, 1e-3, batches of 64),
in the crop field for 30 epochs (``dronefl image-baseline``; the closed loop's pretraining) and
for E epochs per update in the closed loop.

Output slot ``j`` is the scenario's ``j``-th target: its position at ``t + 1`` relative to the
drone's odometry position at ``t``. The frame says where each target is only through the colour
of its vehicle, so the model must learn detection, identity and motion at once; the head is
scaled by the altitude (a camera's ground footprint grows with it), the one physical prior it is
given.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from dronefl.logs import GroundTruth, OnboardLog
from dronefl.models.model import sinusoidal_positions
from dronefl.models.windows import ALTITUDE_SCALE_M

#: Odometry features per step: altitude / ALTITUDE_SCALE_M, vx, vy (m/s).
ODOMETRY_FEATURES = 3


@dataclass(frozen=True)
class ImageTraining:
    """How the image model trains: Adam at ``lr`` on batches of ``batch_size`` windows for
    ``epochs`` passes (shuffled with ``seed``); set a priori (the paper gives none), not tuned."""

    epochs: int = 30
    lr: float = 1e-3
    batch_size: int = 64
    seed: int = 0


@dataclass(frozen=True)
class ImageModelConfig:
    """Architecture of :class:`FrameTransformer`: ``n_targets`` output slots, ``past_steps``
    L_p frames per window, frames of ``frame_px`` x ``frame_px`` RGB pixels, one stride-2
    3 x 3 convolution per entry of ``channels``, a transformer encoder of ``n_layers`` layers
    of width ``d_model`` (``n_heads`` heads, feed-forward ``d_ff``), ``dropout``."""

    n_targets: int
    past_steps: int = 10
    frame_px: int = 48
    channels: tuple[int, ...] = (16, 32, 64, 64)
    d_model: int = 64
    n_heads: int = 4
    n_layers: int = 2
    d_ff: int = 128
    dropout: float = 0.1

    def __post_init__(self) -> None:
        for name in ("n_targets", "past_steps", "frame_px", "d_model", "n_heads", "n_layers"):
            if getattr(self, name) < 1:
                raise ValueError(f"ImageModelConfig.{name} must be >= 1, got {getattr(self, name)}")
        if not self.channels or min(self.channels) < 1:
            raise ValueError(f"ImageModelConfig.channels must be positive, got {self.channels}")
        if self.frame_px < 2 ** len(self.channels):
            raise ValueError(
                f"ImageModelConfig.frame_px {self.frame_px} is too small for "
                f"{len(self.channels)} stride-2 convolutions"
            )
        if self.d_model % self.n_heads:
            raise ValueError("ImageModelConfig.d_model must be a multiple of n_heads")


class FrameTransformer(nn.Module):
    """Frames and odometry of L_p steps -> every target's position at t + 1 (module doc)."""

    def __init__(self, config: ImageModelConfig) -> None:
        super().__init__()
        self.config = config
        layers: list[nn.Module] = []
        width, size = 3, config.frame_px
        for channels in config.channels:
            layers += [nn.Conv2d(width, channels, 3, stride=2, padding=1), nn.ReLU()]
            width, size = channels, math.ceil(size / 2)
        self.encoder = nn.Sequential(
            *layers, nn.Flatten(), nn.Linear(width * size * size, config.d_model)
        )
        self.odometry = nn.Linear(ODOMETRY_FEATURES, config.d_model)
        layer = nn.TransformerEncoderLayer(
            config.d_model, config.n_heads, config.d_ff, config.dropout, batch_first=True
        )
        self.transformer = nn.TransformerEncoder(layer, config.n_layers, enable_nested_tensor=False)
        self.head = nn.Linear(config.d_model, 2 * config.n_targets)
        positions = sinusoidal_positions(torch.arange(config.past_steps), config.d_model)
        self.register_buffer("positions", positions, persistent=False)

    def forward(self, frames: torch.Tensor, odometry: torch.Tensor) -> torch.Tensor:
        """``frames`` ``(B, L_p, P, P, 3)`` uint8, ``odometry`` ``(B, L_p, 3)`` ->
        ``(B, n_targets, 2)`` m, each target at t + 1 relative to the drone at t."""
        b, steps = frames.shape[:2]
        pixels = frames.reshape(b * steps, *frames.shape[2:]).permute(0, 3, 1, 2).float() / 255.0
        x = self.encoder(pixels).reshape(b, steps, -1) + self.odometry(odometry)
        x = self.transformer(x + self.positions[:steps])
        scale = odometry[:, -1, 0, None, None]  # z_t / ALTITUDE_SCALE_M
        return self.head(x[:, -1]).reshape(b, self.config.n_targets, 2) * scale


@dataclass(frozen=True)
class FrameWindows:
    """Training windows of one or more drones, over shared frame stores.

    ``frames`` ``(F, P, P, 3)`` uint8: every frame once; ``index`` ``(W, L_p)``: the frames of
    each window (oldest first); ``odometry`` ``(W, L_p, 3)``; ``label`` ``(W, N, 2)`` m: each
    target at t + 1 relative to the drone at t; ``mask`` ``(W, N)``: the slots that count (the
    drone's assigned targets in view at t); ``drone`` ``(W,)`` the drone id of each window.
    """

    frames: np.ndarray
    index: np.ndarray
    odometry: np.ndarray
    label: np.ndarray
    mask: np.ndarray
    drone: np.ndarray

    def __len__(self) -> int:
        return len(self.index)

    def subset(self, rows: np.ndarray) -> FrameWindows:
        """The windows ``rows`` (same frame store)."""
        return FrameWindows(
            self.frames, self.index[rows], self.odometry[rows], self.label[rows],
            self.mask[rows], self.drone[rows],
        )  # fmt: skip

    @staticmethod
    def concat(parts: list[FrameWindows]) -> FrameWindows:
        """One set of windows over the frames of all ``parts``."""
        offsets = np.cumsum([0] + [len(p.frames) for p in parts[:-1]])
        return FrameWindows(
            np.concatenate([p.frames for p in parts]),
            np.concatenate([p.index + o for p, o in zip(parts, offsets, strict=True)]),
            np.concatenate([p.odometry for p in parts]),
            np.concatenate([p.label for p in parts]),
            np.concatenate([p.mask for p in parts]),
            np.concatenate([p.drone for p in parts]),
        )


def frame_windows(
    frames: np.ndarray,
    odometry: np.ndarray,
    visible: np.ndarray,
    target_position: np.ndarray,
    drone_id: int,
    past_steps: int,
    stride: int = 1,
) -> FrameWindows:
    """Every window of one drone's run: ``frames`` ``(K, P, P, 3)`` uint8, ``odometry`` ``(K,
    12)`` (the log's vector: x, y, z, vx, vy, ...), ``visible`` ``(K, N)`` the assigned targets
    the drone sees at each step, ``target_position`` ``(K, N, 2)`` m the labels (truth or
    pseudo-labels; NaN: none). A window ends at every ``stride``-th step ``t`` (``L_p - 1 <= t
    <= K - 2``); its ``mask`` may be empty (nothing visible to learn from)."""
    k = len(frames)
    ends = np.arange(past_steps - 1, k - 1, stride)
    label = target_position[ends + 1] - odometry[ends, None, 0:2]
    mask = visible[ends] & np.isfinite(label).all(axis=-1)
    index = ends[:, None] + np.arange(-past_steps + 1, 1)[None, :]
    features = odometry_features(odometry)
    return FrameWindows(
        frames, index, features[index], np.nan_to_num(label).astype(np.float32), mask,
        np.full(len(ends), drone_id),
    )  # fmt: skip


def odometry_features(odometry: np.ndarray) -> np.ndarray:
    """The model's odometry input ``(K, 3)`` float32 from the log's odometry ``(K, 12)`` (x, y,
    z, vx, vy, ...): ``[z / ALTITUDE_SCALE_M, vx, vy]``."""
    odometry = np.asarray(odometry)
    return np.stack(
        [odometry[:, 2] / ALTITUDE_SCALE_M, odometry[:, 3], odometry[:, 4]], axis=-1
    ).astype(np.float32)


def recorded_frame_windows(
    logs: dict[int, OnboardLog],
    truth: GroundTruth,
    frames: np.ndarray,
    drone_ids: tuple[int, ...],
    past_steps: int,
) -> dict[int, FrameWindows]:
    """Every drone's windows of a recorded run (one ending at every step), labelled by the
    truth: ``frames`` ``(M, K, P, P, 3)`` in ``drone_ids`` order; a slot counts where the drone
    detected its assigned target at t (the mask the model learns from)."""
    out = {}
    for i, drone_id in enumerate(drone_ids):
        log = logs[drone_id]
        out[drone_id] = frame_windows(
            frames[i], log.odometry.astype(np.float64), log.detected & log.assigned[None, :],
            truth.target_position, drone_id, past_steps,
        )  # fmt: skip
    return out


def chronological_rows(
    data: FrameWindows, stride: int, train_fraction: float
) -> tuple[np.ndarray, np.ndarray]:
    """The rows of one drone's every-step windows ``data`` (:func:`recorded_frame_windows`)
    with something to learn from, split in time: every ``stride``-th window whose label lies
    in the first ``train_fraction`` of the steps (training), and every window after (held
    out)."""
    end = data.index[:, -1]
    split = int((end.max() + 2) * train_fraction)
    usable = data.mask.any(axis=1)
    train = np.flatnonzero((end < split - 1) & usable & (end % stride == 0))
    return train, np.flatnonzero((end >= split - 1) & usable)


@dataclass(frozen=True)
class ImageTrainStats:
    """``loss`` per epoch (masked MSE, m^2), wall ``seconds`` per epoch."""

    loss: tuple[float, ...]
    seconds_per_epoch: float


def _batch(data: FrameWindows, rows: np.ndarray) -> tuple[torch.Tensor, ...]:
    return (
        torch.from_numpy(data.frames[data.index[rows]]),
        torch.from_numpy(data.odometry[rows]),
        torch.from_numpy(data.label[rows]),
        torch.from_numpy(data.mask[rows]),
    )


def _masked_mse(predicted: torch.Tensor, label: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared distance (m^2) over the masked slots."""
    squared = ((predicted - label) ** 2).sum(-1)
    return (squared * mask).sum() / mask.sum().clamp(min=1)


def train_image_model(
    model: FrameTransformer,
    data: FrameWindows,
    training: ImageTraining,
    on_epoch: Callable[[int], None] | None = None,
) -> ImageTrainStats:
    """Adam on the masked MSE over ``data`` as ``training`` says (a fresh optimiser);
    ``on_epoch(epoch)`` after each epoch (1, 2, ...)."""
    if len(data) == 0:
        raise ValueError("no training windows")
    rng = np.random.default_rng(training.seed)
    torch.manual_seed(training.seed)
    optimizer = torch.optim.Adam(model.parameters(), lr=training.lr)
    losses, started = [], time.perf_counter()
    model.train()
    batch_size = training.batch_size
    for _ in range(training.epochs):
        total, weight = 0.0, 0.0
        order = rng.permutation(len(data))
        for start in range(0, len(data), batch_size):
            frames, odometry, label, mask = _batch(data, order[start : start + batch_size])
            loss = _masked_mse(model(frames, odometry), label, mask)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            n = float(mask.sum())
            total, weight = total + loss.item() * n, weight + n
        losses.append(total / max(weight, 1.0))
        if on_epoch is not None:
            on_epoch(len(losses))
    model.eval()
    return ImageTrainStats(tuple(losses), (time.perf_counter() - started) / training.epochs)


@torch.no_grad()
def predict_windows(
    model: FrameTransformer, data: FrameWindows, rows: np.ndarray, batch_size: int = 256
) -> np.ndarray:
    """``model``'s predictions ``(len(rows), N, 2)`` m for the windows ``rows`` of ``data``,
    in batches of ``batch_size`` (dropout off)."""
    model.eval()
    out = []
    for start in range(0, len(rows), batch_size):
        part = rows[start : start + batch_size]
        frames = torch.from_numpy(data.frames[data.index[part]])
        out.append(model(frames, torch.from_numpy(data.odometry[part])).numpy())
    return np.concatenate(out) if out else np.zeros((0, model.config.n_targets, 2))


def evaluate_image_model(model: FrameTransformer, data: FrameWindows) -> dict[int, float]:
    """Masked MSE (m^2) of ``model`` on ``data``, per drone id."""
    predicted = predict_windows(model, data, np.arange(len(data)))
    squared = ((predicted - data.label) ** 2).sum(-1) * data.mask
    out = {}
    for drone in np.unique(data.drone):
        mine = data.drone == drone
        if data.mask[mine].any():
            out[int(drone)] = float(squared[mine].sum() / data.mask[mine].sum())
    return out
