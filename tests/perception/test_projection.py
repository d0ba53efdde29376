"""Camera geometry and the projection detector, checked against hand calculations."""

import math

import numpy as np
import pytest

from dronefl.config import VehicleSpec, load_scenario
from dronefl.perception.projection import (
    ProjectionDetector,
    ProjectionNoise,
    vehicle_boxes,
    vehicle_corners,
)
from dronefl.sim.camera import PinholeCamera
from dronefl.sim.environment import FarmEnvironment
from dronefl.types import CameraView, TargetState

CAMERA = PinholeCamera.from_spec()  # 1280 x 720, 80 deg HFOV
VEHICLE = VehicleSpec()  # 4 x 2 x 1.5 m
EXACT = ProjectionNoise(center_px=0.0, size_frac=0.0, miss_base=0.0, miss_per_m=0.0)


def boxes_at(altitude, positions, headings=None):
    positions = np.atleast_2d(positions).astype(float)
    headings = np.zeros(len(positions)) if headings is None else np.asarray(headings)
    return vehicle_boxes(
        CAMERA, VEHICLE, np.array([50.0, 50.0, altitude]), 0.0, positions, headings
    )


def test_focal_length_and_footprint():
    f = 640 / math.tan(math.radians(40))
    assert CAMERA.focal_px == pytest.approx(f)
    hx, hy = CAMERA.footprint_half_extent(30.0)
    assert hx == pytest.approx(30 * math.tan(math.radians(40)))
    assert hy == pytest.approx(30 * 360 / f)


def test_target_at_nadir_projects_to_image_centre():
    boxes, inside = boxes_at(30.0, [50.0, 50.0])
    assert boxes[0, :2] == pytest.approx([0.5, 0.5])
    assert inside[0] == pytest.approx(1.0)


def test_box_size_scales_with_inverse_altitude():
    # A flat 4 x 2 m plate seen from h: width = f * 4 / h / 1280 (the roof at 1.5 m is nearer).
    for h in (20.0, 40.0, 80.0):
        boxes, _ = boxes_at(h, [50.0, 50.0])
        w_expected = CAMERA.focal_px * VEHICLE.length / (h - VEHICLE.height) / 1280
        h_expected = CAMERA.focal_px * VEHICLE.width / (h - VEHICLE.height) / 720
        assert boxes[0, 2] == pytest.approx(w_expected, rel=1e-9)
        assert boxes[0, 3] == pytest.approx(h_expected, rel=1e-9)
    small, _ = boxes_at(80.0 + VEHICLE.height, [50.0, 50.0])
    large, _ = boxes_at(40.0 + VEHICLE.height, [50.0, 50.0])
    assert large[0, 2] / small[0, 2] == pytest.approx(2.0)


def test_north_is_image_up_and_east_is_image_right():
    boxes, _ = boxes_at(30.0, [[60.0, 50.0], [50.0, 60.0]])
    assert boxes[0, 0] > 0.5 and boxes[0, 1] == pytest.approx(0.5)
    assert boxes[1, 1] < 0.5 and boxes[1, 0] == pytest.approx(0.5)


def test_back_projection_inverts_projection():
    uv, _ = CAMERA.project(np.array([[61.0, 43.0, 0.0]]), np.array([50.0, 50.0, 30.0]))
    assert CAMERA.ground_point(uv, np.array([50.0, 50.0, 30.0]))[0] == pytest.approx([61, 43])


def test_vehicle_outside_or_half_outside_the_image():
    hx, _ = CAMERA.footprint_half_extent(30.0)
    _, inside = boxes_at(30.0, [[50.0 + hx + 10, 50.0], [50.0 + hx, 50.0]])
    assert inside[0] == 0.0
    # Centred on the footprint's edge: the ground half is in, the roof (nearer the camera,
    # so projected further out) is less than half in.
    assert 0.35 < inside[1] < 0.5


def view_of(target_xy, camera_xyz, heading=0.0):
    target = TargetState(1, np.array(target_xy, float), np.zeros(2), heading)
    return CameraView(1, 0.0, np.array(camera_xyz, float), 0.0, (target,))


def detector(kind="crop_field", noise=EXACT, seed=0):
    env = FarmEnvironment(kind, load_scenario("case1").field)
    return ProjectionDetector(CAMERA, VEHICLE, env, np.random.default_rng(seed), noise)


def test_exact_detector_reports_the_projected_box():
    (det,) = detector().detect(view_of([52.5, 47.5], [50.0, 50.0, 30.0]))
    expected, _ = boxes_at(30.0, [52.5, 47.5])
    assert det.target_id == 1
    assert det.box == pytest.approx(tuple(expected[0]))


def test_canopy_hides_a_vehicle_under_it_but_not_in_the_open():
    # Tree rows lie on lane boundaries y = 5 k; trees every 4 m from x = 20; canopy r = 1.6 m.
    under_tree, in_alley = [40.0, 5.0], [40.0, 7.5]
    orchard, crop = detector("orchard"), detector("crop_field")
    assert orchard.detect(view_of(under_tree, [40.0, 5.0, 30.0])) == ()
    assert len(crop.detect(view_of(under_tree, [40.0, 5.0, 30.0]))) == 1
    assert len(orchard.detect(view_of(in_alley, [40.0, 7.5, 30.0]))) == 1


def test_canopies_hide_more_of_a_vehicle_seen_at_a_slant():
    env = FarmEnvironment("orchard", load_scenario("case1").field)
    roof = vehicle_corners(VEHICLE, np.array([[40.0, 8.5]]), np.zeros(1), z=(1.0,), grid=(5, 3))
    overhead = env.visible(np.array([40.0, 8.5, 30.0]), roof).mean()
    slanted = env.visible(np.array([40.0, 18.5, 30.0]), roof).mean()  # 10 m north
    # Hand count on the 5 x 3 roof grid: 4 points under the row's canopies from above, 7 when
    # the rays lean north over the next canopy row.
    assert overhead == pytest.approx(11 / 15)
    assert slanted == pytest.approx(8 / 15)


def test_miss_probability_grows_with_range():
    noise = ProjectionNoise(
        center_px=0.0, size_frac=0.0, miss_base=0.0, miss_per_m=0.01, miss_range0=20.0
    )
    det = detector(noise=noise, seed=1)
    near = np.mean([len(det.detect(view_of([50, 50], [50, 50, 20.0]))) for _ in range(400)])
    far = np.mean([len(det.detect(view_of([50, 50], [50, 50, 70.0]))) for _ in range(400)])
    assert near == pytest.approx(1.0, abs=0.02)  # slant 18.5 m < 20 m: never missed
    assert far == pytest.approx(1 - 0.01 * (68.5 - 20), abs=0.08)


def test_box_jitter_has_the_configured_std_in_pixels():
    noise = ProjectionNoise(center_px=2.0, size_frac=0.05, miss_base=0.0, miss_per_m=0.0)
    det = detector(noise=noise, seed=2)
    exact, _ = boxes_at(30.0, [50.0, 50.0])
    boxes = np.array([det.detect(view_of([50, 50], [50, 50, 30.0]))[0].box for _ in range(2000)])
    assert ((boxes[:, 0] - exact[0, 0]) * 640).std() == pytest.approx(2.0, rel=0.1)
    assert (boxes[:, 2] / exact[0, 2]).std() == pytest.approx(0.05, rel=0.1)
