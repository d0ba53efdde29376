"""Perception test helpers shared by the detector tests."""

from collections.abc import Callable

import numpy as np
import pytest

from dronefl.perception.base import Detector
from dronefl.perception.dataset import label_scene
from dronefl.perception.evaluation import iou_xywh
from dronefl.sim.world import World
from dronefl.types import CameraView


def _check_all_visible_found(world: World, detector: Detector, view: CameraView) -> int:
    """Detect in ``view`` and check every vehicle the projection rule calls visible: found
    under its own id, IoU >= 0.5 with its projected box. Returns their number."""
    truth = label_scene(
        world.camera, world.scenario, world.environment, view.camera_position, view.yaw,
        view.targets, min_visible=0.5,
    )  # fmt: skip
    found = {d.target_id: np.array(d.box) for d in detector.detect(view)}
    for target_id, box in zip(truth.target_ids, truth.boxes, strict=True):
        assert target_id in found, f"target {target_id} missed at {view.camera_position}"
        assert iou_xywh(found[target_id], box) >= 0.5, f"target {target_id} box off"
    return len(truth.target_ids)


@pytest.fixture
def assert_all_visible_found() -> Callable[[World, Detector, CameraView], int]:
    """``check(world, detector, view) -> n``: every visible vehicle found (see above)."""
    return _check_all_visible_found
