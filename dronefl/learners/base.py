"""How a closed-loop method's models learn during an episode (paper Sec. IV-D, Table I).

A :class:`Learner` is given every drone's onboard record and the training labels for the steps
recorded so far, every ``fl_period`` s, and returns the new weights of the predictor the episode
runs (:class:`ModelUpdate`), or ``None`` when the method never updates its models. Class
attributes say what the episode must provide:

* ``model_kind``: which pretrained model the method starts from (``dronefl``: the small
  position-invariant model on every drone; ``centralized``: the large model in the cloud);
* ``federated``: whether its updates are Flower rounds (the episode then runs inside one Flower
  session and hands the learner the session's round driver);
* ``cloud_predicts``: whether the drones send their raw inputs and the cloud predicts (the
  centralized baselines) instead of each drone predicting on board;
* ``model_input``: what the method's model reads: ``boxes`` (detections and odometry) or
  ``frames`` (camera frames and odometry: the learner then receives every frame and predicts
  itself, as :class:`~dronefl.learners.image.CentralizedImageLearner`).

Adding a method is one subclass here and one line in :data:`dronefl.learners.LEARNERS`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

import numpy as np
import torch

from dronefl.fl.records import FlSettings, online_settings
from dronefl.models.online import OnboardRecord
from dronefl.settings import Setting

if TYPE_CHECKING:
    from dronefl.fl.server_app import RoundDriver


@dataclass(frozen=True)
class LearnerSetup:
    """What a learner is built from: the episode folder ``out``, the pretrained weights
    ``state``, the ``setting`` (its model, training and learning sub-configs: windows L_p ->
    1 every ``learning.stride`` samples, ``learning.epochs`` per update, the training's
    optimiser, lr and batch), the episode's ``seed``, the scenario's field ``field_m`` =
    (width, height) m, for a federated learner the episode's Flower round ``driver``, and
    whether the episode is ``resumed`` from a checkpoint (the files of the updates before it
    are then kept)."""

    out: Path
    state: dict[str, torch.Tensor]
    setting: Setting
    seed: int
    field_m: tuple[float, float]
    driver: RoundDriver | None = None
    resumed: bool = False

    def fl_settings(self, method: str, run_dir: str = "", out_dir: str = "") -> FlSettings:
        """The training settings of ``method``'s updates
        (:func:`~dronefl.fl.records.online_settings`)."""
        return online_settings(self.setting, method, self.seed, self.field_m, run_dir, out_dir)


@dataclass(frozen=True)
class ModelUpdate:
    """The result of one update: the new weights, the training loss per drone (``0`` for the
    cloud; scaled MSE), the drones whose update was left out (``"<id>: <reason>"``) and the
    model bytes each drone received (``down``) and sent (``up``)."""

    state: dict[str, torch.Tensor]
    train_loss: dict[int, float]
    rejected: tuple[str, ...] = ()
    weight_bytes_down: dict[int, int] = field(default_factory=dict)
    weight_bytes_up: dict[int, int] = field(default_factory=dict)


class Learner(ABC):
    """Updates the episode's predictor from the data recorded so far."""

    model_kind: ClassVar[str] = "dronefl"
    federated: ClassVar[bool] = False
    cloud_predicts: ClassVar[bool] = False
    model_input: ClassVar[str] = "boxes"

    def __init__(self, setup: LearnerSetup) -> None:
        self.setup = setup

    @abstractmethod
    def update(
        self, records: list[OnboardRecord], labels: np.ndarray, server_round: int
    ) -> ModelUpdate | None:
        """Learn from ``records``, record ``i`` labelled by ``labels[i]`` ``(steps, N, 2)`` m
        (``labels`` ``(M, steps, N, 2)``; column j is target ``records[0].target_ids[j]``; NaN
        where that drone has no label) in update number
        ``server_round`` (1, 2, ...); ``None`` if the method does not update its models."""

    def state(self) -> object:
        """What the learner carries from one update to the next (weights, round history), as
        numpy arrays and plain Python values (:func:`dronefl.io.save_state`'s kinds), for an
        episode checkpoint (:mod:`dronefl.experiments.loop_checkpoint`); ``None`` (the
        default): nothing. Runtime objects (the Flower driver) are not part of it: the resumed
        episode builds new ones."""
        return None

    def restore(self, state: object) -> None:
        """Continue from ``state``, a :meth:`state` of a learner built with the same setup."""
        if state is not None:
            raise ValueError(f"{type(self).__name__} carries no state to restore, got {state!r}")


def weights_to_arrays(state: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
    """Model weights as numpy arrays (copies), for a checkpoint."""
    return {k: v.detach().cpu().numpy().copy() for k, v in state.items()}


def arrays_to_weights(arrays: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """:func:`weights_to_arrays` back as tensors."""
    return {k: torch.from_numpy(np.array(v, copy=True)) for k, v in arrays.items()}
