"""The drone's onboard record in the closed loop: it grows every step (SPEC §8).

:class:`OnboardRecord` keeps exactly what a drone stores (boxes, detection mask, confidences,
odometry; never images) in preallocated arrays, hands the last ``L_p`` steps to the
:class:`~dronefl.models.predictor.TrajectoryPredictor`, and turns everything recorded so far into
an :class:`~dronefl.logs.OnboardLog`, the format FL clients train on.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from dronefl.logs import OnboardLog
from dronefl.types import Detection, Odometry


class OnboardRecord:
    """One drone's onboard data for ``capacity`` steps; column ``j`` is ``target_ids[j]``."""

    def __init__(
        self,
        drone_id: int,
        altitude: float,
        target_ids: Sequence[int],
        assigned: Sequence[int],
        capacity: int,
        meta: dict,
    ) -> None:
        self.drone_id, self.altitude, self.meta = drone_id, altitude, meta
        self.target_ids = np.asarray(target_ids, dtype=np.int32)
        self.assigned = np.isin(self.target_ids, assigned)
        self.column = {int(i): j for j, i in enumerate(self.target_ids)}
        n = len(self.target_ids)
        self.t = np.zeros(capacity)
        self.odometry = np.zeros((capacity, 12))
        self.boxes = np.full((capacity, n, 4), np.nan)
        self.detected = np.zeros((capacity, n), dtype=bool)
        self.confidence = np.zeros((capacity, n))
        self.steps = 0

    def append(self, odometry: Odometry, detections: Sequence[Detection]) -> None:
        """Store one step's odometry and detections."""
        k = self.steps
        if k >= len(self.t):
            raise IndexError(f"drone {self.drone_id}: onboard record is full ({k} steps)")
        self.t[k], self.odometry[k] = odometry.t, odometry.vector
        for d in detections:
            j = self.column[d.target_id]
            self.boxes[k, j], self.detected[k, j], self.confidence[k, j] = d.box, True, d.confidence
        self.steps += 1

    def window(self, past_steps: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The last ``past_steps`` steps of the assigned targets: odometry ``(L_p, 12)``,
        boxes ``(L_p, n, 4)`` and detected ``(L_p, n)``; ``None`` before ``past_steps`` steps."""
        k = self.steps
        if k < past_steps:
            return None
        window = slice(k - past_steps, k)
        return (
            self.odometry[window],
            self.boxes[window][:, self.assigned],
            self.detected[window][:, self.assigned],
        )

    def state(self) -> dict:
        """What was recorded so far (arrays and the step count), for an episode checkpoint."""
        k = self.steps
        return {
            "steps": k, "t": self.t[:k].copy(), "odometry": self.odometry[:k].copy(),
            "boxes": self.boxes[:k].copy(), "detected": self.detected[:k].copy(),
            "confidence": self.confidence[:k].copy(),
        }  # fmt: skip

    def restore(self, state: dict) -> None:
        """Continue from ``state`` (:meth:`state` of a record of the same drone); its steps
        must fit this record's capacity."""
        k = int(state["steps"])
        if k > len(self.t):
            raise ValueError(f"drone {self.drone_id}: {k} recorded steps exceed {len(self.t)}")
        for name in ("t", "odometry", "boxes", "detected", "confidence"):
            getattr(self, name)[:k] = state[name]
        self.steps = k

    def to_log(self) -> OnboardLog:
        """Everything recorded so far as an onboard log (copies)."""
        k = self.steps
        return OnboardLog(
            self.drone_id,
            self.altitude,
            self.t[:k].copy(),
            self.odometry[:k].astype(np.float32),
            self.target_ids,
            self.assigned,
            self.boxes[:k].copy(),
            self.detected[:k].copy(),
            self.confidence[:k].copy(),
            self.meta,
        )
