"""Downward-looking pinhole camera (SPEC §2).

The camera hangs below the drone on a gimbal that keeps it pointing straight down (nadir) and
turns it with the drone's yaw ``psi``. With the camera at ``c`` (m) and a world point ``p``,

    X = (p - c) . e_u,   Y = (p - c) . e_v,   depth = c_z - p_z
    u = (c_x_px + f X / depth) / W_px,       v = (c_y_px + f Y / depth) / H_px

where ``e_u = (cos psi, sin psi, 0)`` is image-right and ``e_v = (sin psi, -cos psi, 0)``
image-down (so with ``psi = 0`` image-right is east and image-up is north), ``f`` the focal
length in pixels, and ``(u, v)`` the normalised image coordinates that survive the resize to the
square detector image unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dronefl.config import CameraSpec


@dataclass(frozen=True)
class PinholeCamera:
    """Pinhole intrinsics: ``width_px`` x ``height_px`` sensor with ``hfov_deg`` horizontal FOV."""

    width_px: int
    height_px: int
    hfov_deg: float
    detector_px: int

    @classmethod
    def from_spec(cls, spec: CameraSpec | None = None) -> PinholeCamera:
        """The camera a scenario describes (default: :class:`CameraSpec`'s defaults)."""
        spec = spec or CameraSpec()
        return cls(spec.width_px, spec.height_px, spec.hfov_deg, spec.detector_px)

    @property
    def focal_px(self) -> float:
        """Focal length in sensor pixels, ``f = (W/2) / tan(hfov/2)``."""
        return (self.width_px / 2) / math.tan(math.radians(self.hfov_deg) / 2)

    @property
    def vfov_deg(self) -> float:
        """Vertical field of view, degrees."""
        return math.degrees(2 * math.atan((self.height_px / 2) / self.focal_px))

    def footprint_half_extent(self, height_above: float) -> tuple[float, float]:
        """Half-width (along image-right) and half-height (along image-down) of the ground
        footprint, m, for a camera ``height_above`` m above the ground plane."""
        k = height_above / self.focal_px
        return self.width_px / 2 * k, self.height_px / 2 * k

    def project(
        self, points: np.ndarray, camera_position: np.ndarray, yaw: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Project world points ``(..., 3)`` m to normalised image coordinates.

        Returns ``uv`` ``(..., 2)`` in ``[0, 1]`` for points inside the image (values outside
        that range lie outside it) and ``depth`` ``(...)`` m along the optical axis.
        """
        d = points - camera_position
        cos_y, sin_y = math.cos(yaw), math.sin(yaw)
        x_img = d[..., 0] * cos_y + d[..., 1] * sin_y
        y_img = d[..., 0] * sin_y - d[..., 1] * cos_y
        depth = -d[..., 2]
        f = self.focal_px
        u = 0.5 + f * x_img / (depth * self.width_px)
        v = 0.5 + f * y_img / (depth * self.height_px)
        return np.stack([u, v], axis=-1), depth

    def ground_point(
        self, uv: np.ndarray, camera_position: np.ndarray, yaw: float = 0.0, ground_z: float = 0.0
    ) -> np.ndarray:
        """Back-project normalised image points ``(..., 2)`` onto the plane ``z = ground_z``;
        returns world ``(..., 2)`` m. The inverse of :meth:`project` for that plane."""
        depth = camera_position[2] - ground_z
        f = self.focal_px
        x_img = (uv[..., 0] - 0.5) * self.width_px * depth / f
        y_img = (uv[..., 1] - 0.5) * self.height_px * depth / f
        cos_y, sin_y = math.cos(yaw), math.sin(yaw)
        dx = x_img * cos_y + y_img * sin_y
        dy = x_img * sin_y - y_img * cos_y
        return np.stack([camera_position[0] + dx, camera_position[1] + dy], axis=-1)
