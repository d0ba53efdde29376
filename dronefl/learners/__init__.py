"""Closed-loop methods: how each one's models learn during an episode.

:data:`LEARNERS` maps a method name (``dronefl track --method``) to its :class:`Learner`.
"""

from dronefl.learners.base import Learner, LearnerSetup, ModelUpdate
from dronefl.learners.centralized import CentralizedLearner
from dronefl.learners.federated import FederatedLearner
from dronefl.learners.fixed import FixedLearner
from dronefl.learners.image import CentralizedImageLearner

LEARNERS: dict[str, type[Learner]] = {
    "centralized": CentralizedLearner,
    "fixed": FixedLearner,
    "dronefl": FederatedLearner,
    "centralized-image": CentralizedImageLearner,
}

__all__ = ["LEARNERS", "Learner", "LearnerSetup", "ModelUpdate"]
