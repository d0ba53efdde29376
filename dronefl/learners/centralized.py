"""The centralized baseline's online learning: the cloud retrains its large model on the
pooled data of every drone (paper Table I)."""

from __future__ import annotations

import numpy as np

from dronefl.learners.base import (
    Learner,
    LearnerSetup,
    ModelUpdate,
    arrays_to_weights,
    weights_to_arrays,
)
from dronefl.logs import PseudoLabels
from dronefl.models.model import build_model
from dronefl.models.online import OnboardRecord
from dronefl.models.train import TrainConfig, train_pooled
from dronefl.models.windows import WindowSpec, build_windows


class CentralizedLearner(Learner):
    """The large model, trained in the cloud for E epochs on every drone's windows pooled."""

    model_kind = "centralized"
    cloud_predicts = True

    def __init__(self, setup: LearnerSetup) -> None:
        super().__init__(setup)
        self.settings = setup.fl_settings("centralized")
        self.model = build_model(self.settings.model)
        self.model.load_state_dict(setup.state)

    def update(
        self, records: list[OnboardRecord], labels: np.ndarray, server_round: int
    ) -> ModelUpdate:
        setup = self.setup
        past_steps, learning = setup.setting.model.past_steps, setup.setting.learning
        spec = WindowSpec(past_steps, 1, relative=True, stride=learning.stride)
        windows = []
        for record, own in zip(records, labels, strict=True):
            log = record.to_log()
            pseudo = PseudoLabels(log.t, record.target_ids, own[: len(log.t)])
            windows.append(build_windows(log, pseudo.for_log(log), spec))
        seed = setup.seed * 1_000_003 + server_round
        train = TrainConfig(
            learning.epochs, self.settings.lr, self.settings.batch_size, seed,
            self.settings.optimizer,
        )  # fmt: skip
        stats = train_pooled(self.model, windows, train)
        return ModelUpdate(self.model.state_dict(), {0: stats.loss})

    def state(self) -> dict[str, np.ndarray]:
        """The large model's current weights (it trains on from them in the next update)."""
        return weights_to_arrays(self.model.state_dict())

    def restore(self, state: dict[str, np.ndarray]) -> None:
        """Continue from the weights ``state``."""
        self.model.load_state_dict(arrays_to_weights(state))
