"""Messages of the deployment besides the radio link's wire formats (:mod:`dronefl.wire`).

The drone <-> cloud link carries exactly what the simulated episode counts:
:class:`~dronefl.wire.PredictionMessage` up and :class:`~dronefl.wire.ControlMessage` down.
The rest is the simulator standing in for hardware, or the FL round's data, packed
little-endian with :mod:`struct` like the wire formats:

``SenseMessage`` (world -> drone: the drone's sensors at step k; f64 so that the drone sees
exactly the numbers the simulated episode's drone sees)::

    u32 step | f64 t (s) | 12 x f64 odometry | u8 n | n x (u8 target_id | 4 x f64 box | f64 conf)

``TelemetryMessage`` (world -> cloud: every drone's autopilot state at step k, what the
planner reads; the simulated episode reads the same states from the world object)::

    u32 step | f64 t (s) | u8 m | m x (u8 drone_id | f64 x, y (m) | f64 vx, vy (m/s)
                                      | f64 altitude (m) | f64 ax, ay (m/s^2))

``Release`` (cloud -> world: step k is planned, and the FL round after it is over)::

    u32 step

``LabelsMessage`` (cloud -> drone before an FL round: the fused tracks of steps 0 .. T-1, the
pseudo-labels the drone trains on)::

    u16 round | u32 T | u8 N | N x u8 target_id | T x N x 2 x f32 position (m, NaN: no track)
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from dronefl.types import Detection, DroneState, Odometry
from dronefl.wire import WireError

_SENSE_HEAD = struct.Struct("<Id12dB")
_SENSE_BOX = struct.Struct("<B5d")
_TELEMETRY_HEAD = struct.Struct("<IdB")
_TELEMETRY_DRONE = struct.Struct("<B7d")
_RELEASE = struct.Struct("<I")
_LABELS_HEAD = struct.Struct("<HIB")


def _check_size(name: str, data: bytes, expected: int) -> None:
    if len(data) != expected:
        raise WireError(f"{name} of {len(data)} bytes, expected {expected}")


@dataclass(frozen=True)
class SenseMessage:
    """One drone's odometry and detections at ``step``."""

    step: int
    odometry: Odometry
    detections: tuple[Detection, ...]

    def encode(self) -> bytes:
        head = _SENSE_HEAD.pack(
            self.step, self.odometry.t, *self.odometry.vector, len(self.detections)
        )
        boxes = (_SENSE_BOX.pack(d.target_id, *d.box, d.confidence) for d in self.detections)
        return head + b"".join(boxes)

    @classmethod
    def decode(cls, data: bytes) -> SenseMessage:
        if len(data) < _SENSE_HEAD.size:
            raise WireError(f"sense message of {len(data)} bytes is shorter than its header")
        step, t, *rest = _SENSE_HEAD.unpack_from(data)
        vector, n = np.array(rest[:12]), rest[12]
        _check_size("sense message", data, _SENSE_HEAD.size + n * _SENSE_BOX.size)
        detections = []
        for k in range(n):
            target_id, *box, confidence = _SENSE_BOX.unpack_from(
                data, _SENSE_HEAD.size + k * _SENSE_BOX.size
            )
            detections.append(Detection(target_id, tuple(box), confidence))
        return cls(step, Odometry(t, vector), tuple(detections))


@dataclass(frozen=True)
class TelemetryMessage:
    """Every drone's true kinematic state at ``step`` (time ``t`` s)."""

    step: int
    t: float
    drones: tuple[DroneState, ...]

    def encode(self) -> bytes:
        parts = [_TELEMETRY_HEAD.pack(self.step, self.t, len(self.drones))]
        for d in self.drones:
            parts.append(
                _TELEMETRY_DRONE.pack(
                    d.drone_id, *d.position, *d.velocity, d.altitude, *d.acceleration
                )
            )
        return b"".join(parts)

    @classmethod
    def decode(cls, data: bytes) -> TelemetryMessage:
        if len(data) < _TELEMETRY_HEAD.size:
            raise WireError(f"telemetry of {len(data)} bytes is shorter than its header")
        step, t, m = _TELEMETRY_HEAD.unpack_from(data)
        _check_size("telemetry", data, _TELEMETRY_HEAD.size + m * _TELEMETRY_DRONE.size)
        drones = []
        for k in range(m):
            drone_id, x, y, vx, vy, altitude, ax, ay = _TELEMETRY_DRONE.unpack_from(
                data, _TELEMETRY_HEAD.size + k * _TELEMETRY_DRONE.size
            )
            drones.append(
                DroneState(
                    drone_id, np.array([x, y]), np.array([vx, vy]), altitude, np.array([ax, ay])
                )
            )
        return cls(step, t, tuple(drones))


def encode_release(step: int) -> bytes:
    return _RELEASE.pack(step)


def decode_release(data: bytes) -> int:
    _check_size("release", data, _RELEASE.size)
    return _RELEASE.unpack(data)[0]


@dataclass(frozen=True)
class LabelsMessage:
    """The fused tracks ``position`` ``(T, N, 2)`` m of steps ``0 .. T-1`` for ``server_round``
    (NaN where the drone has no label); column ``j`` is ``target_ids[j]``."""

    server_round: int
    target_ids: tuple[int, ...]
    position: np.ndarray

    def encode(self) -> bytes:
        steps, n, _ = self.position.shape
        head = _LABELS_HEAD.pack(self.server_round, steps, n)
        ids = bytes(self.target_ids)
        return head + ids + np.ascontiguousarray(self.position, dtype="<f4").tobytes()

    @classmethod
    def decode(cls, data: bytes) -> LabelsMessage:
        if len(data) < _LABELS_HEAD.size:
            raise WireError(f"labels message of {len(data)} bytes is shorter than its header")
        server_round, steps, n = _LABELS_HEAD.unpack_from(data)
        start = _LABELS_HEAD.size + n
        _check_size("labels message", data, start + steps * n * 2 * 4)
        ids = tuple(data[_LABELS_HEAD.size : start])
        position = np.frombuffer(data, dtype="<f4", offset=start).reshape(steps, n, 2)
        return cls(server_round, ids, position.astype(np.float64))
