"""Local training and evaluation of the trajectory predictor: plain PyTorch, no FL imports.

Loss and metric are the mean squared error in m^2, averaged over windows, future steps and the
two horizontal axes (``torch.nn.functional.mse_loss``). Optimiser: Adam, lr 1e-3, E = 10 epochs
(paper Sec. V-A). Batch size 128 windows: small enough for many updates per epoch on a drone's
few thousand windows, large enough that one epoch of 3,000 windows stays near 0.3 s on one CPU
thread.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from dronefl.models.windows import BOX_DIM, FEATURE_DIM, WindowSet
from dronefl.settings import OPTIMIZERS

#: Extra loss term computed from the model being trained (e.g. FedProx's proximal term).
Regularizer = Callable[[nn.Module], torch.Tensor]
SGD_MOMENTUM = 0.9


@dataclass(frozen=True)
class TrainConfig:
    """Local training: ``epochs`` E, learning rate ``lr``, ``batch_size`` windows, the
    ``seed`` of the shuffling and dropout, the ``optimizer``: ``adam`` (the paper's) or
    ``sgd`` (with momentum 0.9), started afresh by every call, and ``detection_gaps``: the
    probability that a window is trained on with a gap cut into its detections
    (:func:`cut_detection_gaps`; 0: the windows as recorded)."""

    epochs: int = 10
    lr: float = 1e-3
    batch_size: int = 128
    seed: int = 0
    optimizer: str = "adam"
    detection_gaps: float = 0.0

    def __post_init__(self) -> None:
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(
                f"TrainConfig.optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}"
            )
        if self.epochs < 1 or self.batch_size < 1:
            raise ValueError("TrainConfig.epochs and batch_size must be >= 1")
        if not self.lr > 0:
            raise ValueError(f"TrainConfig.lr must be positive, got {self.lr}")
        if not 0.0 <= self.detection_gaps <= 1.0:
            raise ValueError(
                f"TrainConfig.detection_gaps must be in [0, 1], got {self.detection_gaps}"
            )


@dataclass(frozen=True)
class TrainStats:
    """What one local training run reports: ``num_examples`` windows, the mean loss of the
    last epoch in m^2 (without the regulariser) and the seconds per epoch."""

    num_examples: int
    loss: float
    seconds_per_epoch: float


def proximal_term(reference: dict[str, torch.Tensor], mu: float) -> Regularizer:
    """FedProx's proximal term (Li et al., 2020): ``(mu / 2) * sum_k ||w_k - w_k^g||^2``
    over the model's trainable parameters ``w``, against the round's global weights
    ``reference`` (a state dict; held fixed). Its gradient is ``mu (w - w^g)``."""
    frozen = {k: v.detach().clone() for k, v in reference.items()}

    def term(model: nn.Module) -> torch.Tensor:
        total = torch.zeros(())
        for name, w in model.named_parameters():
            if name in frozen:
                total = total + (w - frozen[name]).pow(2).sum()
        return 0.5 * mu * total

    return term


def drift_correction(server: dict[str, torch.Tensor], own: dict[str, torch.Tensor]) -> Regularizer:
    """SCAFFOLD's corrected local step (Karimireddy et al., 2020) as a loss term
    ``sum_k <c_k - c_i,k, w_k>`` over the parameters named in ``server``: its gradient
    ``c - c_i`` is added to every local gradient, so the drone steps along
    ``g_i(w) - c_i + c``, its own gradient with its bias against the federation's removed.
    ``server`` is the cloud's control variate c, ``own`` the drone's c_i (both fixed)."""
    correction = {k: (server[k] - own[k]).detach().clone() for k in server}

    def term(model: nn.Module) -> torch.Tensor:
        total = torch.zeros(())
        for name, w in model.named_parameters():
            if name in correction:
                total = total + (w * correction[name]).sum()
        return total

    return term


def local_steps(num_examples: int, config: TrainConfig) -> int:
    """Optimiser steps K of one :func:`train_local` call on ``num_examples`` windows."""
    return config.epochs * -(-num_examples // config.batch_size)


def updated_control_variate(
    own: dict[str, torch.Tensor],
    server: dict[str, torch.Tensor],
    start: dict[str, torch.Tensor],
    end: dict[str, torch.Tensor],
    steps: int,
    config: TrainConfig,
) -> dict[str, torch.Tensor]:
    """SCAFFOLD's option II: the drone's new control variate, the mean (corrected) gradient
    of its ``steps`` local steps from the global weights ``start`` to its weights ``end``,
    ``c_i+ = c_i - c + (x - y_i) / (K lr_eff)``.

    ``lr_eff = lr / (1 - beta)`` for SGD with momentum beta (a steady gradient g moves the
    weights by lr g / (1 - beta) per step); the estimate assumes plain or momentum SGD, which
    is why SCAFFOLD runs refuse Adam (:class:`dronefl.fl.records.FlSettings`)."""
    if config.optimizer != "sgd":
        raise ValueError("SCAFFOLD's control variate needs optimizer 'sgd'")
    scale = (1.0 - SGD_MOMENTUM) / (steps * config.lr)
    return {k: own[k] - server[k] + scale * (start[k] - end[k]).detach() for k in server}


def _tensors(data: WindowSet) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return (
        torch.from_numpy(data.features),
        torch.from_numpy(data.altitude),
        torch.from_numpy(data.labels),
    )


#: Offset of the generator that cuts detection gaps from the shuffling's seed, so that a run
#: with gaps visits the windows in the same order as one without.
GAP_SEED_OFFSET = 7_919


def cut_detection_gaps(
    features: torch.Tensor, probability: float, generator: torch.Generator
) -> torch.Tensor:
    """``features`` (B, L, FEATURE_DIM) with, in each window with probability
    ``probability``, one run of missed detections cut in, as a tree or the edge of the image
    hides a target: ``m ~ U{1..L-1}`` consecutive steps starting at ``s ~ U{0..L-m}`` lose
    their box (the four box features 0) and their ``detected`` flag, the odometry kept. A
    window that would be left without any detection keeps its own. A model pretrained where
    targets are never hidden (the crop field) sees such windows only after deployment
    (docs/fusion.md, "Windows with gaps in pretraining"). Returns a new tensor."""
    batch, steps, _ = features.shape
    if probability <= 0.0 or steps < 2:
        return features
    chosen = torch.rand(batch, generator=generator) < probability
    length = torch.randint(1, steps, (batch,), generator=generator)
    start = (torch.rand(batch, generator=generator) * (steps - length + 1)).long()
    index = torch.arange(steps)
    hidden = (index >= start[:, None]) & (index < (start + length)[:, None]) & chosen[:, None]
    detected = features[..., FEATURE_DIM - 1] > 0.5
    hidden &= ((detected & ~hidden).any(dim=1))[:, None]  # never hide a window's last one
    out = features.clone()
    out[..., :BOX_DIM] = out[..., :BOX_DIM].masked_fill(hidden[..., None], 0.0)
    out[..., FEATURE_DIM - 1] = out[..., FEATURE_DIM - 1].masked_fill(hidden, 0.0)
    return out


def train_local(
    model: nn.Module,
    data: WindowSet,
    config: TrainConfig,
    regularizer: Regularizer | None = None,
) -> TrainStats:
    """Train ``model`` in place for ``config.epochs`` epochs of MSE on ``data``.

    Minimises ``MSE(model(x, h), y) + regularizer(model)``; the data are shuffled each epoch
    with a generator seeded by ``config.seed`` (dropout uses the same seed), and each batch
    gets its detection gaps (``config.detection_gaps``) from a generator of its own.
    """
    if len(data) == 0:
        raise ValueError("train_local: no training windows")
    features, altitude, labels = _tensors(data)
    if config.optimizer == "adam":
        optimiser = torch.optim.Adam(model.parameters(), lr=config.lr, fused=True)
    else:
        optimiser = torch.optim.SGD(model.parameters(), lr=config.lr, momentum=SGD_MOMENTUM)
    generator = torch.Generator().manual_seed(config.seed)
    gaps = torch.Generator().manual_seed(config.seed + GAP_SEED_OFFSET)
    torch.manual_seed(config.seed)
    model.train()
    n = len(data)
    started = time.perf_counter()
    epoch_loss = float("nan")
    for _ in range(config.epochs):
        order = torch.randperm(n, generator=generator)
        total = 0.0
        for i in range(0, n, config.batch_size):
            idx = order[i : i + config.batch_size]
            inputs = cut_detection_gaps(features[idx], config.detection_gaps, gaps)
            prediction = model(inputs, altitude[idx])  # (b, L_f, 2) m
            loss = F.mse_loss(prediction, labels[idx])
            objective = loss if regularizer is None else loss + regularizer(model)
            optimiser.zero_grad(set_to_none=True)
            objective.backward()
            optimiser.step()
            total += float(loss.detach()) * idx.numel()
        epoch_loss = total / n
    return TrainStats(n, epoch_loss, (time.perf_counter() - started) / config.epochs)


def train_pooled(model: nn.Module, window_sets: list[WindowSet], config: TrainConfig) -> TrainStats:
    """Centralized training: ``model`` trained in the cloud on every drone's windows pooled
    into one set (the centralized baselines of Fig. 5 and Table I)."""
    return train_local(model, WindowSet.concat(window_sets), config)


@torch.no_grad()
def evaluate(model: nn.Module, data: WindowSet, batch_size: int = 1024) -> float:
    """Test MSE in m^2 of ``model`` on ``data`` (dropout off)."""
    if len(data) == 0:
        raise ValueError("evaluate: no test windows")
    features, altitude, labels = _tensors(data)
    model.eval()
    total = 0.0
    for i in range(0, len(data), batch_size):
        prediction = model(features[i : i + batch_size], altitude[i : i + batch_size])
        total += float(F.mse_loss(prediction, labels[i : i + batch_size], reduction="sum"))
    return total / labels.numel()
