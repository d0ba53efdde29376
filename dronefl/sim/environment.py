"""Farm environments: the static geometry of ``crop_field``, ``orchard`` and ``open``.

* ``crop_field``: low crop rows run east-west; vehicles drive the lanes between them and turn
  in the headlands. Nothing hides a vehicle from above.
* ``orchard``: a row of trees on every lane boundary (``y = k * lane_spacing``), one tree every
  ``tree_spacing`` m between the headlands. Each canopy is a vertical cylinder of radius
  ``canopy_radius`` between ``canopy_bottom`` and ``canopy_top`` m; a ray from a camera to a
  point of a vehicle that passes through a canopy is blocked.
* ``open``: bare ground, for experiments without structure.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dronefl.config import Environment, FieldSpec


@dataclass(frozen=True)
class FarmEnvironment:
    """Static geometry of the field. Lengths in m."""

    kind: Environment
    field: FieldSpec
    tree_spacing: float = 4.0
    canopy_radius: float = 1.6
    canopy_bottom: float = 1.8
    canopy_top: float = 4.5

    @property
    def tree_row_y(self) -> np.ndarray:
        """North coordinates of the tree rows (orchard) or crop-row boundaries, m: ``(R,)``."""
        return np.arange(1, self.field.n_lanes) * self.field.lane_spacing

    @property
    def tree_x(self) -> np.ndarray:
        """East coordinates of the trees along each row, m: ``(C,)``."""
        f = self.field
        n = int(np.floor((f.width - 2 * f.headland) / self.tree_spacing)) + 1
        return f.headland + self.tree_spacing * np.arange(n)

    @property
    def trees(self) -> np.ndarray:
        """Trunk positions ``(K, 2)`` m; empty unless ``kind == 'orchard'``."""
        if self.kind != "orchard":
            return np.zeros((0, 2))
        xx, yy = np.meshgrid(self.tree_x, self.tree_row_y)
        return np.stack([xx.ravel(), yy.ravel()], axis=-1)

    def visible(self, camera_position: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Line-of-sight test from a camera ``(3,)`` to world points ``(..., 3)``.

        Returns a boolean array ``(...)``: ``True`` where no canopy blocks the ray. The ray
        ``P(s) = p + s (c - p)`` is inside the canopy layer for ``s`` in ``[s0, s1]``; it is
        blocked if the horizontal segment ``P(s0) -> P(s1)`` passes within ``canopy_radius`` of
        a trunk. Only the trees of the 4 nearest rows x 3 nearest columns around the segment's
        midpoint are tested (the segment is at most a few metres long).
        """
        if self.kind != "orchard":
            return np.ones(points.shape[:-1], dtype=bool)
        shape = points.shape[:-1]
        p = points.reshape(-1, 3)
        rise = camera_position[2] - p[:, 2]
        s0 = np.clip((self.canopy_bottom - p[:, 2]) / rise, 0.0, 1.0)
        s1 = np.clip((self.canopy_top - p[:, 2]) / rise, 0.0, 1.0)
        d = camera_position[:2] - p[:, :2]  # (R, 2)
        a = p[:, :2] + s0[:, None] * d
        b = p[:, :2] + s1[:, None] * d
        mid = 0.5 * (a + b)
        spacing = self.field.lane_spacing
        rows = np.floor(mid[:, 1] / spacing)[:, None] + np.array([-1, 0, 1, 2])  # (R, 4)
        row_ok = (rows >= 1) & (rows <= self.field.n_lanes - 1)
        col0 = np.round((mid[:, 0] - self.field.headland) / self.tree_spacing)[:, None]
        cols = col0 + np.array([-1, 0, 1])  # (R, 3)
        col_ok = (cols >= 0) & (cols < self.tree_x.size)
        tx = (self.field.headland + cols * self.tree_spacing)[:, None, :]  # (R, 1, 3)
        ty = (rows * spacing)[:, :, None]  # (R, 4, 1)
        valid = row_ok[:, :, None] & col_ok[:, None, :]  # (R, 4, 3)
        dist = _segment_point_distance(a[:, None, None, :], b[:, None, None, :], tx, ty)
        blocked = ((dist < self.canopy_radius) & valid & (s1 > s0)[:, None, None]).any(axis=(1, 2))
        return ~blocked.reshape(shape)


def _segment_point_distance(
    a: np.ndarray, b: np.ndarray, cx: np.ndarray, cy: np.ndarray
) -> np.ndarray:
    """Distance from points ``(cx, cy)`` to segments ``a -> b`` (``(..., 2)``; all arguments
    broadcast over the leading axes), m."""
    abx, aby = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    acx, acy = cx - a[..., 0], cy - a[..., 1]
    s = np.clip((acx * abx + acy * aby) / np.maximum(abx * abx + aby * aby, 1e-12), 0.0, 1.0)
    return np.hypot(acx - s * abx, acy - s * aby)
