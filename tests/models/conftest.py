"""A tiny hand-made onboard log: one drone hovering at (10, 20) m, 30 m up, over 16 steps;
target 1 (assigned) drives east at 1 m per step from (0, 0) m, target 2 is not assigned."""

import numpy as np
import pytest

from dronefl.logs import OnboardLog


@pytest.fixture
def tiny_log() -> tuple[OnboardLog, np.ndarray]:
    steps = 16
    odometry = np.zeros((steps, 12), dtype=np.float32)
    odometry[:, 0:3] = (10.0, 20.0, 30.0)
    boxes = np.full((steps, 2, 4), np.nan, dtype=np.float32)
    boxes[:, 0] = (0.4, 0.6, 0.05, 0.03)
    detected = np.zeros((steps, 2), dtype=bool)
    detected[:, 0] = True
    detected[4:9, 0] = False  # target 1 missed for 5 steps
    labels = np.zeros((steps, 2, 2))
    labels[:, 0, 0] = np.arange(steps)  # target 1 at (k, 0) m at step k
    labels[:, 1] = (50.0, 50.0)
    log = OnboardLog(
        drone_id=1,
        altitude=30.0,
        t=np.arange(steps) * 0.2,
        odometry=odometry,
        target_ids=np.array([1, 2], dtype=np.int32),
        assigned=np.array([True, False]),
        boxes=boxes,
        detected=detected,
        confidence=detected.astype(np.float32),
        meta={},
    )
    return log, labels
