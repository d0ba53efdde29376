"""JPEG frames on the centralized baseline's uplink: the codec round trip, its validation, and
the cloud's YOLO still finding every visible vehicle in the decoded frame."""

import numpy as np
import pytest

from dronefl.config import load_scenario
from dronefl.perception.evaluation import iou_xywh
from dronefl.perception.render import SceneRenderer
from dronefl.perception.uplink import (
    DEFAULT_JPEG_QUALITY,
    CloudVisionDetector,
    FrameUplink,
    decode_jpeg,
    downscale,
    encode_jpeg,
)
from dronefl.sim.world import World
from dronefl.types import CameraView, TargetState

SCENARIO = load_scenario("case3")


@pytest.fixture(scope="module")
def frame() -> np.ndarray:
    """Drone 3's (30 m) Case 3 frame in the crop field at t = 0, seed 0."""
    world = World(SCENARIO, environment="crop_field", seed=0)
    renderer = SceneRenderer.from_scenario(SCENARIO, world.environment)
    image = renderer.render_view(world.camera_views()[2])
    renderer.close()
    return image


def test_round_trip_keeps_shape_and_stays_close(frame: np.ndarray) -> None:
    decoded = decode_jpeg(encode_jpeg(frame, DEFAULT_JPEG_QUALITY))
    assert decoded.shape == (640, 640, 3) and decoded.dtype == np.uint8
    error = decoded.astype(float) - frame
    # Measured on this frame: mean |error| 2.5 of 255, PSNR 36 dB (the soil speckle is the
    # hardest part for JPEG).
    assert np.abs(error).mean() <= 3.0
    assert 10 * np.log10(255**2 / np.mean(error**2)) >= 35.0


def test_higher_quality_means_more_bytes(frame: np.ndarray) -> None:
    sizes = [len(encode_jpeg(frame, q)) for q in (50, 75, 90, 95)]
    assert sizes == sorted(sizes) and len(set(sizes)) == 4
    assert sizes[2] < frame.nbytes / 5  # q90 is > 5x smaller than the raw 1.2 MB frame


@pytest.mark.parametrize("quality", [0, 96, -5, 90.0, True, "90"])
def test_bad_quality_is_refused(frame: np.ndarray, quality: object) -> None:
    with pytest.raises(ValueError, match="quality"):
        encode_jpeg(frame, quality)
    with pytest.raises(ValueError, match="quality"):
        CloudVisionDetector.for_world(World(SCENARIO, seed=0), quality=quality)


@pytest.mark.parametrize(
    "image",
    [np.zeros((8, 8, 3), dtype=np.float32), np.zeros((8, 8), dtype=np.uint8),
     np.zeros((8, 8, 4), dtype=np.uint8), [[0, 0, 0]]],
)  # fmt: skip
def test_bad_image_is_refused(image: object) -> None:
    with pytest.raises(ValueError, match="image"):
        encode_jpeg(image, DEFAULT_JPEG_QUALITY)


def test_bad_bytes_are_refused(frame: np.ndarray) -> None:
    data = encode_jpeg(frame, DEFAULT_JPEG_QUALITY)
    for bad in (b"not a jpeg", data[: len(data) // 2]):
        with pytest.raises(ValueError, match="not a readable JPEG"):
            decode_jpeg(bad)
    with pytest.raises(ValueError, match="expected JPEG bytes"):
        decode_jpeg(frame)


@pytest.mark.parametrize("environment", ["crop_field", "orchard"])
def test_cloud_finds_every_visible_target_in_the_decoded_frame(
    environment: str, assert_all_visible_found
) -> None:
    world = World(SCENARIO, environment=environment, seed=0)
    detector = CloudVisionDetector.for_world(world)
    checked = sum(assert_all_visible_found(world, detector, v) for v in world.camera_views())
    detector.renderer.close()
    assert checked >= 6  # the frames do show vehicles


def test_hand_made_crop_field_scene_at_quality_50(assert_all_visible_found) -> None:
    world = World(SCENARIO, environment="crop_field", seed=0)
    detector = CloudVisionDetector.for_world(world, quality=50)
    targets = tuple(
        TargetState(i, np.array([62.0 + 6.0 * i, SCENARIO.field.lane_y(10 + i % 3)]),
                    np.zeros(2), np.pi * (i % 2))
        for i in SCENARIO.target_ids
    )  # fmt: skip
    view = CameraView(1, 0.0, np.array([80.0, 62.5, 30.0]), 0.0, targets)
    assert assert_all_visible_found(world, detector, view) == 6
    detector.renderer.close()


def test_bytes_sent_are_the_encoded_frames() -> None:
    world = World(SCENARIO, environment="crop_field", seed=0)
    detector = CloudVisionDetector.for_world(world)
    views = world.camera_views()
    expected = {}
    for view in (*views, views[0]):  # drone 1 sends twice
        frame = detector.renderer.render_view(view)
        detector.detect(view)
        n_bytes = len(encode_jpeg(frame, DEFAULT_JPEG_QUALITY))
        assert detector.last_frame_bytes == n_bytes
        expected[view.drone_id] = expected.get(view.drone_id, 0) + n_bytes
    assert detector.bytes_sent == expected
    detector.renderer.close()


def test_a_frame_carried_by_the_view_is_sent_as_is(frame: np.ndarray) -> None:
    world = World(SCENARIO, environment="crop_field", seed=0)
    detector = CloudVisionDetector.for_world(world, quality=75)
    view = CameraView(7, 0.0, np.array([0.0, 0.0, 30.0]), 0.0, (), image=frame)
    detections = detector.detect(view)
    detector.renderer.close()
    assert detector.last_frame_bytes == len(encode_jpeg(frame, 75))
    assert detector.bytes_sent == {7: detector.last_frame_bytes}
    # The cloud detects on the JPEG it received, not on the drone's raw frame: at quality 75 it
    # still finds the same vehicles as on the raw frame, each box within IoU 0.8 of the raw one.
    on_raw = {d.target_id: np.array(d.box) for d in detector.yolo.detect_image(frame)}
    on_jpeg = {d.target_id: np.array(d.box) for d in detections}
    assert on_raw and set(on_jpeg) == set(on_raw)
    for target_id, box in on_raw.items():
        assert iou_xywh(on_jpeg[target_id], box) >= 0.8


def test_downscale_averages_the_pixels_each_output_pixel_covers() -> None:
    image = np.zeros((4, 4, 3), dtype=np.uint8)
    image[:2, :2] = 200  # the top-left quarter
    image[2:, 2:, 0] = 100  # red in the bottom-right quarter
    image[0, 3] = 40  # one pixel of the top-right quarter

    small = downscale(image, 2)

    assert small.shape == (2, 2, 3) and small.dtype == np.uint8
    np.testing.assert_array_equal(small[0, 0], [200, 200, 200])
    np.testing.assert_array_equal(small[1, 1], [100, 0, 0])
    np.testing.assert_array_equal(small[0, 1], [10, 10, 10])  # 40 / 4
    np.testing.assert_array_equal(small[1, 0], [0, 0, 0])


def test_the_frame_uplink_sends_the_jpeg_and_keeps_it_small_in_the_cloud(frame) -> None:
    world = World(SCENARIO, environment="crop_field", seed=0)
    uplink = FrameUplink.for_world(world, frame_px=48)
    view = CameraView(7, 0.0, np.array([0.0, 0.0, 30.0]), 0.0, (), image=frame)

    detections = uplink.detect(view)
    uplink.close()

    data = encode_jpeg(frame, DEFAULT_JPEG_QUALITY)
    assert detections == ()  # the drones detect nothing: the frame is the message
    assert uplink.last_frame_bytes == len(data)
    assert uplink.bytes_sent == {7: len(data)}
    np.testing.assert_array_equal(uplink.last_frame, downscale(decode_jpeg(data), 48))
    with pytest.raises(ValueError, match="frame_px"):
        FrameUplink(uplink.renderer, frame_px=0)
