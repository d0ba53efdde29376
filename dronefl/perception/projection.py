"""The ``projection`` detector: the geometry of a perfect detector plus a measured noise model.

Each vehicle is a box ``length x width x height`` m on the ground, turned to its heading. Its
8 corners are projected through the :class:`~dronefl.sim.camera.PinholeCamera`; the detection
box is the image-aligned hull of those corners clipped to the image. A vehicle is reported if

* the visible fraction ``inside_fraction x unoccluded_fraction >= min_visible`` (nothing
  outside the image, nothing hidden under orchard canopies: a 5 x 3 grid of points on the
  vehicle's roof, 1 m apart, is tested for line of sight), and
* it is not randomly missed: ``P(miss) = miss_base + miss_per_m * max(0, r - miss_range0)``
  with ``r`` the slant range from the camera, m.

Reported boxes carry jitter: the centre moves by ``N(0, center_px^2)`` detector pixels per axis
and width/height scale by ``1 + N(0, size_frac^2)``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import numpy as np

from dronefl.config import VehicleSpec
from dronefl.perception.base import Detector
from dronefl.serialize import from_json
from dronefl.sim.camera import PinholeCamera
from dronefl.sim.environment import FarmEnvironment
from dronefl.types import CameraView, Detection

#: Where the noise parameters fitted to the YOLO detector's measured errors are shipped.
FITTED_NOISE_ASSET = "projection_noise.json"


@dataclass(frozen=True)
class ProjectionNoise:
    """Noise model of the projection detector (units: detector px, m, probabilities)."""

    center_px: float = 1.5
    size_frac: float = 0.04
    miss_base: float = 0.01
    miss_per_m: float = 0.001
    miss_range0: float = 30.0
    min_visible: float = 0.5

    @classmethod
    def fitted(cls) -> ProjectionNoise:
        """The parameters fitted to the shipped YOLO detector, or the hand-set defaults if no
        fit ships with the package."""
        asset = resources.files("dronefl") / "assets" / FITTED_NOISE_ASSET
        if not asset.is_file():
            return cls()
        return from_json(FittedNoise, json.loads(asset.read_text())).params


@dataclass(frozen=True)
class FittedNoise:
    """The shipped fit (``projection_noise.json``): the ``params`` fitted to the detector
    ``weights`` (file name), the hand-set ones ``before``, and the ``source`` of the data."""

    params: ProjectionNoise
    before: ProjectionNoise
    source: str
    weights: str


def vehicle_corners(
    vehicle: VehicleSpec,
    positions: np.ndarray,
    headings: np.ndarray,
    z: tuple[float, ...] = (0.0, 1.0),
    grid: tuple[int, int] = (2, 2),
) -> np.ndarray:
    """World points on each vehicle's box: ``(N, grid[0] * grid[1] * len(z), 3)`` m.

    ``grid`` points along and across the vehicle span its footprint ((2, 2): the corners);
    ``z`` are fractions of the vehicle height.
    """
    local = _local_points(vehicle.length, vehicle.width, vehicle.height, tuple(z), grid)
    cos_h, sin_h = np.cos(headings)[:, None], np.sin(headings)[:, None]  # (N, 1)
    x = positions[:, None, 0] + cos_h * local[:, 0] - sin_h * local[:, 1]
    y = positions[:, None, 1] + sin_h * local[:, 0] + cos_h * local[:, 1]
    out = np.empty((*x.shape, 3))
    out[..., 0], out[..., 1], out[..., 2] = x, y, local[:, 2]
    return out


@lru_cache(maxsize=32)
def _local_points(
    length: float, width: float, height: float, z: tuple[float, ...], grid: tuple[int, int]
) -> np.ndarray:
    """Points on a vehicle in its own frame (x forward, y left, z up): ``(P, 3)`` m."""
    along = np.linspace(-length / 2, length / 2, grid[0])
    across = np.linspace(-width / 2, width / 2, grid[1])
    a, c, h = np.meshgrid(along, across, np.asarray(z) * height, indexing="ij")
    return np.stack([a.ravel(), c.ravel(), h.ravel()], axis=-1)


def vehicle_boxes(
    camera: PinholeCamera,
    vehicle: VehicleSpec,
    camera_position: np.ndarray,
    yaw: float,
    positions: np.ndarray,
    headings: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact image boxes of vehicles at ``positions`` ``(N, 2)`` m with ``headings`` ``(N,)``.

    Returns ``boxes`` ``(N, 4)`` normalised ``(cx, cy, w, h)`` of the hull clipped to the image
    and ``inside_fraction`` ``(N,)``: the clipped hull's area over the full hull's area (0 for a
    vehicle entirely outside the image).
    """
    corners = vehicle_corners(vehicle, positions, headings)
    uv, _ = camera.project(corners, camera_position, yaw)  # (N, 8, 2)
    lo, hi = uv.min(axis=1), uv.max(axis=1)  # (N, 2)
    area = np.prod(hi - lo, axis=-1)
    lo_c, hi_c = np.clip(lo, 0.0, 1.0), np.clip(hi, 0.0, 1.0)
    clipped = np.prod(np.maximum(hi_c - lo_c, 0.0), axis=-1)
    inside = np.where(area > 0, clipped / np.maximum(area, 1e-12), 0.0)
    boxes = np.concatenate([(lo_c + hi_c) / 2, hi_c - lo_c], axis=-1)
    return boxes, inside


def visible_boxes(
    camera: PinholeCamera,
    vehicle: VehicleSpec,
    environment: FarmEnvironment,
    camera_position: np.ndarray,
    yaw: float,
    positions: np.ndarray,
    headings: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Image boxes ``(N, 4)`` of vehicles and the fraction ``(N,)`` of each that can be seen:
    the part of its hull inside the image times the part of a 5 x 3 grid on its roof (1 m apart)
    with a clear line of sight past the canopies. The one visibility rule of the projection
    detector, the detector data set and the detector evaluation."""
    boxes, inside = vehicle_boxes(camera, vehicle, camera_position, yaw, positions, headings)
    roof = vehicle_corners(vehicle, positions, headings, z=(1.0,), grid=(5, 3))
    return boxes, inside * environment.visible(camera_position, roof).mean(axis=-1)


class ProjectionDetector(Detector):
    """Projects each vehicle's 3-D box into the image and applies :class:`ProjectionNoise`."""

    name = "projection"

    def __init__(
        self,
        camera: PinholeCamera,
        vehicle: VehicleSpec,
        environment: FarmEnvironment,
        rng: np.random.Generator,
        noise: ProjectionNoise | None = None,
    ) -> None:
        self.camera = camera
        self.vehicle = vehicle
        self.environment = environment
        self.noise = noise if noise is not None else ProjectionNoise.fitted()
        self.rng = rng

    def state(self) -> dict:
        """The random generator's state (:meth:`Detector.state`)."""
        return self.rng.bit_generator.state

    def restore(self, state: dict) -> None:
        """Continue the random stream from ``state`` (:meth:`Detector.restore`)."""
        self.rng.bit_generator.state = state

    def detect(self, view: CameraView) -> tuple[Detection, ...]:
        """Detections of the vehicles in ``view`` (uses the true scene, not an image)."""
        if not view.targets:
            return ()
        positions = np.array([t.position for t in view.targets])
        headings = np.array([t.heading for t in view.targets])
        boxes, visible = visible_boxes(
            self.camera,
            self.vehicle,
            self.environment,
            view.camera_position,
            view.yaw,
            positions,
            headings,
        )
        centre = np.concatenate([positions, np.full((len(positions), 1), 0.5)], axis=-1)
        slant = np.linalg.norm(centre - view.camera_position, axis=-1)
        n = self.noise
        p_miss = np.clip(
            n.miss_base + n.miss_per_m * np.maximum(0.0, slant - n.miss_range0), 0.0, 1.0
        )
        # Draw a fixed number of variates per call so that the stream stays aligned.
        draw_miss = self.rng.random(len(positions))
        jitter = self.rng.normal(size=(len(positions), 4))
        detected = (visible >= n.min_visible) & (draw_miss >= p_miss)
        side = self.camera.detector_px
        noisy = boxes.copy()
        noisy[:, :2] += jitter[:, :2] * n.center_px / side
        noisy[:, 2:] *= 1.0 + jitter[:, 2:] * n.size_frac
        noisy[:, :2] = np.clip(noisy[:, :2], 0.0, 1.0)
        noisy[:, 2:] = np.clip(noisy[:, 2:], 1.0 / side, 1.0)
        confidence = np.clip(0.5 + 0.45 * visible - 0.003 * slant, 0.05, 0.99)
        return tuple(
            Detection(
                view.targets[k].target_id, tuple(float(v) for v in noisy[k]), float(confidence[k])
            )
            for k in np.flatnonzero(detected)
        )
