"""The shipped ONNX detector on rendered frames of known states: every visible vehicle is found,
with the right target id, IoU >= 0.5 against its projected box."""

from pathlib import Path

import numpy as np
import pytest

from dronefl.config import load_scenario
from dronefl.perception.dataset import label_scene
from dronefl.perception.render import SceneRenderer
from dronefl.perception.yolo import YoloDetector, letterbox, shipped_detector_path
from dronefl.sim.world import World
from dronefl.types import CameraView, TargetState

SCENARIO = load_scenario("case3")


@pytest.mark.parametrize("environment", ["crop_field", "orchard"])
def test_case3_views_find_every_visible_target(environment: str, assert_all_visible_found) -> None:
    world = World(SCENARIO, environment=environment, seed=0)
    detector = YoloDetector.for_world(world)
    checked = sum(assert_all_visible_found(world, detector, v) for v in world.camera_views())
    assert checked >= 6  # the frames do show vehicles
    detector.renderer.close()


def test_hand_made_crop_field_scene(assert_all_visible_found) -> None:
    world = World(SCENARIO, environment="crop_field", seed=0)
    detector = YoloDetector.for_world(world)
    camera = np.array([80.0, 62.5, 30.0])
    targets = tuple(
        TargetState(i, np.array([62.0 + 6.0 * i, SCENARIO.field.lane_y(10 + i % 3)]),
                    np.zeros(2), np.pi * (i % 2))
        for i in SCENARIO.target_ids
    )  # fmt: skip
    view = CameraView(1, 0.0, camera, 0.0, targets)
    assert assert_all_visible_found(world, detector, view) == 6
    detector.renderer.close()


def test_detections_are_one_per_target_sorted_and_normalised() -> None:
    world = World(SCENARIO, environment="crop_field", seed=0)
    view = world.camera_views()[0]  # drone 1, the highest, over all six vehicles
    renderer = SceneRenderer.from_scenario(SCENARIO, world.environment)
    image = renderer.render_view(view)
    renderer.close()
    truth = label_scene(world.camera, SCENARIO, world.environment, view.camera_position,
                        view.yaw, view.targets, min_visible=0.5)  # fmt: skip
    assert len(truth.target_ids) >= 2  # the frame shows vehicles: the test cannot pass empty
    detections = YoloDetector().detect_image(image)
    ids = [d.target_id for d in detections]
    assert ids == sorted(set(ids)) and set(ids) <= set(SCENARIO.target_ids)
    assert set(truth.target_ids.tolist()) <= set(ids)  # every visible vehicle, under its id
    for d in detections:
        assert all(0.0 <= v <= 1.0 for v in d.box) and 0.0 < d.confidence <= 1.0


def test_letterbox_keeps_aspect() -> None:
    padded, box = letterbox(np.zeros((360, 640, 3), dtype=np.uint8), 320)
    assert padded.shape == (320, 320, 3)
    assert box.scale == 0.5 and box.pad == (0, 70)


def test_bad_weights_give_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="no detector weights"):
        YoloDetector(tmp_path / "missing.onnx")
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(shipped_detector_path().read_bytes()[:1000])
    with pytest.raises(ValueError, match="not a readable ONNX detector"):
        YoloDetector(corrupt)
    with pytest.raises(ValueError, match="no image and the detector has no renderer"):
        YoloDetector().detect(CameraView(1, 0.0, np.array([0.0, 0.0, 30.0]), 0.0, ()))
