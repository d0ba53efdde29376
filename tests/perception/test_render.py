"""Renderer camera geometry: rendered vehicles land where the pinhole projection puts them."""

import numpy as np
import pytest

from dronefl.config import FieldSpec, VehicleSpec
from dronefl.perception.projection import vehicle_boxes
from dronefl.perception.render import SceneRenderer
from dronefl.sim.camera import PinholeCamera
from dronefl.sim.environment import FarmEnvironment
from dronefl.types import TargetState

CAMERA = PinholeCamera.from_spec()
VEHICLE = VehicleSpec()


@pytest.fixture(scope="module")
def renderer() -> SceneRenderer:
    scene = SceneRenderer(CAMERA, VEHICLE, FarmEnvironment("open", FieldSpec()), target_ids=(1,))
    yield scene
    scene.close()


def red_box(image: np.ndarray) -> np.ndarray:
    """Bounding box ``(cx, cy, w, h)`` normalised of the red (target 1) pixels."""
    rgb = image.astype(int)
    ys, xs = np.nonzero(
        (rgb[..., 0] > 60) & (rgb[..., 0] > 2 * rgb[..., 1]) & (rgb[..., 0] > 2 * rgb[..., 2])
    )
    side = image.shape[0]
    x1, x2, y1, y2 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    return np.array([(x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1]) / side


def iou(a: np.ndarray, b: np.ndarray) -> float:
    lo, hi = (
        np.maximum(a[:2] - a[2:] / 2, b[:2] - b[2:] / 2),
        np.minimum(a[:2] + a[2:] / 2, b[:2] + b[2:] / 2),
    )
    inter = np.prod(np.clip(hi - lo, 0, None))
    return inter / (np.prod(a[2:]) + np.prod(b[2:]) - inter)


def test_frame_shape(renderer: SceneRenderer) -> None:
    image = renderer.render(np.array([80.0, 60.0, 40.0]), 0.0, ())
    assert image.shape == (640, 640, 3) and image.dtype == np.uint8


def test_vehicle_at_nadir_lands_at_image_centre(renderer: SceneRenderer) -> None:
    camera = np.array([80.0, 60.0, 30.0])
    image = renderer.render(camera, 0.0, (TargetState(1, camera[:2], np.zeros(2), 0.0),))
    cx, cy, _, _ = red_box(image) * 640
    assert abs(cx - 320) <= 1.0 and abs(cy - 320) <= 1.0


@pytest.mark.parametrize(
    ("offset", "heading", "yaw", "altitude"),
    [((15.0, 5.0), 0.3, 0.0, 30.0),  # east and north: right of and above the centre
     ((-20.0, -8.0), 2.0, 0.0, 60.0),
     ((6.0, 0.0), 0.0, np.pi / 2, 20.0)],  # yaw 90 deg: east appears below the centre
)  # fmt: skip
def test_rendered_box_matches_projection(
    renderer: SceneRenderer, offset: tuple, heading: float, yaw: float, altitude: float
) -> None:
    camera = np.array([80.0, 60.0, altitude])
    position = camera[:2] + np.array(offset)
    image = renderer.render(camera, yaw, (TargetState(1, position, np.zeros(2), heading),))
    projected, inside = vehicle_boxes(
        CAMERA, VEHICLE, camera, yaw, position[None], np.array([heading])
    )
    assert inside[0] == 1.0
    assert iou(red_box(image), projected[0]) > 0.85


def test_yaw_turns_the_image(renderer: SceneRenderer) -> None:
    camera = np.array([80.0, 60.0, 30.0])
    east = (TargetState(1, camera[:2] + [8.0, 0.0], np.zeros(2), 0.0),)
    cx0, cy0 = red_box(renderer.render(camera, 0.0, east))[:2]
    cx1, cy1 = red_box(renderer.render(camera, np.pi / 2, east))[:2]
    assert cx0 > 0.6 and abs(cy0 - 0.5) < 0.02  # right of centre with yaw 0
    assert cy1 > 0.6 and abs(cx1 - 0.5) < 0.02  # below centre with image-right = north


def test_unknown_target_and_bad_camera_raise(renderer: SceneRenderer) -> None:
    with pytest.raises(ValueError, match="not in this scene"):
        renderer.render(
            np.array([0.0, 0.0, 30.0]), 0.0, (TargetState(2, np.zeros(2), np.zeros(2), 0.0),)
        )
    with pytest.raises(ValueError, match="above the vehicles"):
        renderer.render(np.array([0.0, 0.0, 1.0]), 0.0, ())
