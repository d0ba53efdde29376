"""Fixed distributed perception: the pretrained models, never updated (paper Table I)."""

from __future__ import annotations

import numpy as np

from dronefl.learners.base import Learner, ModelUpdate
from dronefl.models.online import OnboardRecord


class FixedLearner(Learner):
    """Every drone keeps its pretrained DroneFL model for the whole episode."""

    def update(
        self, records: list[OnboardRecord], labels: np.ndarray, server_round: int
    ) -> ModelUpdate | None:
        return None
