"""Frozen value types that cross module boundaries (numpy only: no torch, no Flower).

Conventions used everywhere in DroneFL:

* World frame: x east, y north, z up, metres. The field spans ``[0, W] x [0, H]``.
* Time in seconds since the start of a run; one simulation step is ``dt = 1 / rate_hz``.
* Image boxes are ``(cx, cy, w, h)`` normalised to ``[0, 1]`` by the detector image size
  (image x to the right, image y downwards), the YOLO convention.
* Target and drone ids are the 1-based ids of the scenario file.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Layout of the 12-dim odometry vector (SPEC §2).
ODOMETRY_FIELDS: tuple[str, ...] = (
    "x", "y", "z",            # position, m
    "vx", "vy", "vz",         # velocity, m/s
    "roll", "pitch", "yaw",   # attitude, rad
    "p", "q", "r",            # body angular rates, rad/s
)  # fmt: skip
ODOMETRY_DIM = len(ODOMETRY_FIELDS)


@dataclass(frozen=True)
class Odometry:
    """A drone's 12-dim odometry reading at time ``t`` (s), as the flight controller reports it.

    ``vector`` is ``[x, y, z, vx, vy, vz, roll, pitch, yaw, p, q, r]`` in m, m/s, rad, rad/s
    (see :data:`ODOMETRY_FIELDS`); it carries sensor noise.
    """

    t: float
    vector: np.ndarray  # (12,)

    def __post_init__(self) -> None:
        if self.vector.shape != (ODOMETRY_DIM,):
            raise ValueError(f"odometry vector must have shape (12,), got {self.vector.shape}")

    @property
    def position(self) -> np.ndarray:
        """Position ``(x, y, z)`` in m."""
        return self.vector[0:3]

    @property
    def velocity(self) -> np.ndarray:
        """Velocity ``(vx, vy, vz)`` in m/s."""
        return self.vector[3:6]


@dataclass(frozen=True)
class DroneState:
    """True kinematic state of one drone: horizontal double integrator at a fixed altitude.

    ``position`` ``(x, y)`` in m, ``velocity`` ``(vx, vy)`` in m/s, ``altitude`` in m above
    ground, ``acceleration`` the last applied horizontal command in m/s^2.
    """

    drone_id: int
    position: np.ndarray  # (2,)
    velocity: np.ndarray  # (2,)
    altitude: float
    acceleration: np.ndarray = field(default_factory=lambda: np.zeros(2))


@dataclass(frozen=True)
class TargetState:
    """True state of one ground vehicle: ``position``/``velocity`` ``(2,)`` in m and m/s,
    ``heading`` in rad (counter-clockwise from east)."""

    target_id: int
    position: np.ndarray  # (2,)
    velocity: np.ndarray  # (2,)
    heading: float


@dataclass(frozen=True)
class Detection:
    """One detected target in one camera frame.

    ``box`` is ``(cx, cy, w, h)`` normalised to ``[0, 1]`` of the detector image; ``confidence``
    in ``[0, 1]``. A detector reports at most one box per target id (the most confident).
    """

    target_id: int
    box: tuple[float, float, float, float]
    confidence: float


@dataclass(frozen=True)
class CameraView:
    """Everything a detector may look at for one frame of one drone's downward camera.

    A vision detector reads ``image`` (an RGB ``(H, W, 3)`` uint8 frame at the detector size);
    the projection detector reads the true scene (``camera_position`` in m, ``yaw`` in rad and
    ``targets``), which is also what the renderer draws the image from.
    """

    drone_id: int
    t: float
    camera_position: np.ndarray  # (3,) m
    yaw: float
    targets: tuple[TargetState, ...]
    image: np.ndarray | None = None
