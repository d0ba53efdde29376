"""DroneFL's online learning: one Flower round per update (paper Sec. IV-D).

The cloud writes every drone's onboard log so far and the labels to ``<out>/fl/round_<k>/``
(the drones read the folder the round's config names; in a deployment each drone reads its own
disk), and plays one round through the episode's Flower session, continuing from the current
global model; the global checkpoint goes to ``<out>/fl/global/``. A resumed episode keeps that
folder and continues from the global model and round history of its checkpoint.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from dronefl.fl.records import FlSettings, RoundRecord
from dronefl.learners.base import (
    Learner,
    LearnerSetup,
    ModelUpdate,
    arrays_to_weights,
    weights_to_arrays,
)
from dronefl.logs import PseudoLabels
from dronefl.models.online import OnboardRecord


def session_settings(setup: LearnerSetup) -> FlSettings:
    """The Flower settings of an episode's online rounds: the DroneFL model of the setup's
    setting, L_f = 1, the fused tracks as labels, every recorded window trained on (no test
    split, no federated evaluation)."""
    return setup.fl_settings(
        "dronefl", str(setup.out / "fl" / "round_01"), str(setup.out / "fl" / "global")
    )


class FederatedLearner(Learner):
    """FedAvg of the position-invariant AdaIN model through Flower, one round per update."""

    federated = True

    def __init__(self, setup: LearnerSetup) -> None:
        super().__init__(setup)
        if setup.driver is None:
            raise ValueError("the dronefl method needs the episode's Flower round driver")
        self.driver = setup.driver
        self.folder = setup.out / "fl"
        if not setup.resumed:
            shutil.rmtree(self.folder, ignore_errors=True)
        self.weights = setup.state

    def update(
        self, records: list[OnboardRecord], labels: np.ndarray, server_round: int
    ) -> ModelUpdate:
        data = self.folder / f"round_{server_round:02d}"
        write_round_data(data, records, labels)
        self.weights = self.driver.play(self.weights, server_round, run_dir=str(data))
        entry = self.driver.history[-1]
        if entry.server_round != server_round:
            raise RuntimeError(f"federated round {server_round} did not finish")
        # Every drone receives and returns a model of the same size, so the round's train
        # messages split evenly (the diagnostic evaluate messages are not part of the method).
        share = {
            "down": entry.bytes_down.get("train", 0) // len(records),
            "up": entry.bytes_up.get("train", 0) // len(records),
        }
        drones = [r.drone_id for r in records]
        return ModelUpdate(
            state=self.weights,
            train_loss=dict(entry.train_loss),
            rejected=entry.rejected,
            weight_bytes_down={d: share["down"] for d in drones},
            weight_bytes_up={d: share["up"] for d in drones},
        )

    def state(self) -> dict:
        """The global weights, the round history (``history.json``'s entries) and the
        cloud's control variate (SCAFFOLD; ``None`` without)."""
        control = self.driver.control
        return {
            "weights": weights_to_arrays(self.weights),
            "history": [entry.to_json() for entry in self.driver.history],
            "control": None if control is None else weights_to_arrays(control),
        }

    def restore(self, state: dict) -> None:
        """Continue from ``state``: the next round starts from its weights and the server's
        history goes on from its rounds."""
        self.weights = arrays_to_weights(state["weights"])
        self.driver.history = [RoundRecord.from_json(entry) for entry in state["history"]]
        if state["control"] is not None:
            self.driver.control = arrays_to_weights(state["control"])


def write_round_data(folder: Path, records: list[OnboardRecord], labels: np.ndarray) -> None:
    """Every drone's onboard log (``drone_<id>.npz``) and its labels (``tracks_<id>.npz``;
    ``labels`` ``(M, steps, N, 2)`` m in ``records`` order)."""
    folder.mkdir(parents=True, exist_ok=True)
    for record, own in zip(records, labels, strict=True):
        log = record.to_log()
        log.save(folder / f"drone_{record.drone_id}.npz")
        pseudo = PseudoLabels(log.t, record.target_ids, own[: len(log.t)])
        pseudo.save(folder / f"tracks_{record.drone_id}.npz")
