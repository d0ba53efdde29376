"""The paper's centralized baseline: the cloud's image model, retrained on the pooled frames
(paper Sec. V-A, Table I).

Every step each drone sends its camera frame (JPEG) and odometry; the cloud keeps the decoded
frames, downscaled to the model's input (:class:`~dronefl.perception.uplink.FrameUplink`), and
predicts every target each drone is assigned from that drone's last L_p frames with the image
model (:class:`~dronefl.models.image.FrameTransformer`). Nothing detects: the model cannot tell
a target out of view, so it predicts all of them. Every ``fl_period`` s the model trains E
epochs (its own optimiser, :class:`~dronefl.models.image.ImageTraining`: Adam, 1e-3, batches of
64) on the windows of every drone pooled, labelled by the fused tracks, a slot counting where the
drone is assigned the target and has a label.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from dronefl.learners.base import (
    Learner,
    LearnerSetup,
    ModelUpdate,
    arrays_to_weights,
    weights_to_arrays,
)
from dronefl.models.image import (
    FrameTransformer,
    FrameWindows,
    ImageModelConfig,
    ImageTraining,
    frame_windows,
    odometry_features,
    train_image_model,
)
from dronefl.models.model import count_parameters
from dronefl.models.online import OnboardRecord


class CentralizedImageLearner(Learner):
    """The image model in the cloud: it predicts from the frames it receives and learns from
    them (module doc). Its state is the model's weights and every frame received."""

    model_kind = "image"
    cloud_predicts = True
    model_input = "frames"

    def __init__(self, setup: LearnerSetup) -> None:
        super().__init__(setup)
        n_targets = setup.state["head.bias"].shape[0] // 2  # two coordinates per slot
        self.config = ImageModelConfig(n_targets, setup.setting.model.past_steps)
        self.model = FrameTransformer(self.config)
        self.model.load_state_dict(setup.state)
        self.model.eval()
        self.frames: list[list[np.ndarray]] = []

    @property
    def frame_px(self) -> int:
        """Side of the frames the model reads (pixels)."""
        return self.config.frame_px

    @property
    def parameters(self) -> int:
        """The image model's trainable parameters."""
        return count_parameters(self.model)

    def receive(self, i: int, frame: np.ndarray) -> None:
        """Keep drone ``i``'s (its index in the scenario) frame of this step, ``(P, P, 3)``
        uint8, decoded and downscaled in the cloud."""
        while len(self.frames) <= i:
            self.frames.append([])
        self.frames[i].append(frame)

    @torch.no_grad()
    def predict(self, i: int, record: OnboardRecord) -> np.ndarray | None:
        """Drone ``i``'s assigned targets at the next step ``(n_assigned, 2)`` m (world frame)
        from its last L_p frames and odometry; ``None`` before L_p frames have arrived."""
        past = self.config.past_steps
        k = record.steps
        if k < past or len(self.frames[i]) < k:
            return None
        frames = torch.from_numpy(np.stack(self.frames[i][k - past : k]))[None]
        odometry = torch.from_numpy(odometry_features(record.odometry[k - past : k]))[None]
        relative = self.model(frames, odometry)[0].numpy()
        return relative[record.assigned] + record.odometry[k - 1, 0:2]

    def update(
        self, records: list[OnboardRecord], labels: np.ndarray, server_round: int
    ) -> ModelUpdate | None:
        setup = self.setup
        parts = []
        for i, (record, own) in enumerate(zip(records, labels, strict=True)):
            steps = record.steps
            assigned = np.broadcast_to(record.assigned, (steps, len(record.assigned)))
            windows = frame_windows(
                np.stack(self.frames[i][:steps]), record.odometry[:steps], assigned,
                own[:steps], record.drone_id, self.config.past_steps,
                setup.setting.learning.stride,
            )  # fmt: skip
            parts.append(windows.subset(np.flatnonzero(windows.mask.any(axis=1))))
        data = FrameWindows.concat(parts)
        if len(data) == 0:
            return None
        training = dataclasses.replace(
            ImageTraining(),
            epochs=setup.setting.learning.epochs,
            seed=setup.seed * 1_000_003 + server_round,
        )
        stats = train_image_model(self.model, data, training)
        return ModelUpdate(self.model.state_dict(), {0: stats.loss[-1]})

    def state(self) -> dict[str, object]:
        """The model's weights and every frame received so far (``(steps, P, P, 3)`` uint8
        per drone)."""
        return {
            "model": weights_to_arrays(self.model.state_dict()),
            "frames": [np.stack(f) if f else None for f in self.frames],
        }

    def restore(self, state: dict[str, object]) -> None:
        """Continue from ``state`` (:meth:`state`)."""
        self.model.load_state_dict(arrays_to_weights(state["model"]))
        self.model.eval()
        self.frames = [list(f) if f is not None else [] for f in state["frames"]]
