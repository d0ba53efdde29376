"""Wire formats of the per-step messages between drones and the cloud.

Every 0.2 s each drone sends its predictions up and receives its control down. Both are packed
little-endian with :mod:`struct` so that the bytes counted are the bytes a radio would carry
(no framing or transport headers are counted):

``PredictionMessage`` (drone -> cloud), ``9 + 6 n L_f`` bytes for ``n`` predicted targets
over a horizon of ``L_f`` steps::

    u8 version | u8 drone_id | u32 step | u8 horizon L_f | u16 count = n L_f
    count x ( u8 target_id | u8 steps_ahead | i16 x (cm) | i16 y (cm) )

Positions travel as signed centimetres in the world frame: 1 cm resolution (rounding error
<= 5 mm, far below the metre-scale prediction errors) over +-327.67 m, which holds every
field of SPEC §2 with its origin at the field's corner; a prediction beyond that range is
saturated at the edge (the cloud's gate rejects such an outlier anyway).

``ControlMessage`` (cloud -> drone), 14 bytes::

    u8 version | u8 drone_id | u32 step | f32 ax (m/s^2) | f32 ay (m/s^2)

``NoiseReportMessage`` (drone -> cloud, only with the fusion's ``noise_split = reported``;
in the deployment it follows the prediction message in the same payload, :func:`split_uplink`),
``7 + 7 n`` bytes for ``n`` targets: the drone's own estimate of each prediction's error
(:mod:`dronefl.tracking.reports`) as half floats (3 significant digits, up to 65504 m²)::

    u8 version | u8 drone_id | u32 step | u8 count = n
    n x ( u8 target_id | f16 xx | f16 xy | f16 yy )   (m^2)

Raw inputs of the centralized baseline (drone -> cloud), :func:`raw_inputs_message`,
``53 + 17 b`` bytes for ``b`` boxes (none when the cloud detects on the drone's JPEG frame,
which is counted separately)::

    u8 drone_id | u32 step | 12 x f32 odometry | b x ( u8 target_id | 4 x f32 box )

Model weights exchanged by federated learning are counted separately by :mod:`dronefl.fl`.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from dronefl.types import Detection

WIRE_VERSION = 2
_PRED_HEAD = struct.Struct("<BBIBH")
_PRED_ITEM = struct.Struct("<BBhh")
#: Largest |coordinate| a prediction message carries, m (i16 centimetres).
MAX_COORDINATE = 32767 / 100
_CONTROL = struct.Struct("<BBIff")
_NOISE_HEAD = struct.Struct("<BBIB")
_NOISE_ITEM = struct.Struct("<Beee")
_RAW_HEAD = struct.Struct("<BI12f")
_RAW_BOX = struct.Struct("<B4f")


class WireError(ValueError):
    """A message could not be decoded (wrong version, length or content)."""


@dataclass(frozen=True)
class PredictionMessage:
    """One drone's predictions of its targets' next positions at one step.

    ``target_ids`` ``(n,)``; ``positions`` ``(n, L_f, 2)`` m in the world frame.
    """

    drone_id: int
    step: int
    target_ids: tuple[int, ...]
    positions: np.ndarray

    def encode(self) -> bytes:
        """Pack to bytes (format in the module docstring)."""
        n, horizon = len(self.target_ids), self.positions.shape[1]
        parts = [_PRED_HEAD.pack(WIRE_VERSION, self.drone_id, self.step, horizon, n * horizon)]
        centimetres = np.clip(np.rint(np.asarray(self.positions) * 100), -32767, 32767)
        for k, target_id in enumerate(self.target_ids):
            for ahead in range(horizon):
                x, y = centimetres[k, ahead].astype(int)
                parts.append(_PRED_ITEM.pack(target_id, ahead + 1, x, y))
        return b"".join(parts)

    @classmethod
    def decode(cls, data: bytes) -> PredictionMessage:
        """Unpack bytes made by :meth:`encode`; raises :class:`WireError` for anything else
        (wrong version or length, no horizon, items out of order, a target twice)."""
        data = bytes(data)
        if len(data) < _PRED_HEAD.size:
            raise WireError(f"prediction message of {len(data)} bytes is shorter than its header")
        version, drone_id, step, horizon, count = _PRED_HEAD.unpack_from(data)
        if version != WIRE_VERSION:
            raise WireError(f"prediction message version {version}, expected {WIRE_VERSION}")
        if horizon < 1:
            raise WireError("prediction message with a horizon of 0 steps")
        if len(data) != _PRED_HEAD.size + count * _PRED_ITEM.size or count % horizon:
            raise WireError(f"prediction message of {len(data)} bytes does not hold {count} items")
        items = list(_PRED_ITEM.iter_unpack(data[_PRED_HEAD.size :]))
        n = count // horizon  # no targets: (0, L_f, 2) positions
        target_ids = tuple(items[k * horizon][0] for k in range(n))
        for k, (target_id, ahead, _, _) in enumerate(items):
            if target_id != target_ids[k // horizon] or ahead != k % horizon + 1:
                raise WireError(f"prediction message item {k} is out of order")
        if len(set(target_ids)) != n:
            raise WireError("prediction message names a target twice")
        positions = np.array([[x, y] for _, _, x, y in items], dtype=float).reshape(n, horizon, 2)
        positions /= 100.0  # cm -> m
        return cls(drone_id, step, target_ids, positions)


@dataclass(frozen=True)
class ControlMessage:
    """The cloud's acceleration command ``(ax, ay)`` m/s^2 for one drone at one step."""

    drone_id: int
    step: int
    acceleration: tuple[float, float]

    def encode(self) -> bytes:
        """Pack to bytes (format in the module docstring)."""
        return _CONTROL.pack(WIRE_VERSION, self.drone_id, self.step, *self.acceleration)

    @classmethod
    def decode(cls, data: bytes) -> ControlMessage:
        """Unpack bytes made by :meth:`encode`; raises :class:`WireError` for anything else."""
        data = bytes(data)
        if len(data) != _CONTROL.size:
            raise WireError(f"control message must be {_CONTROL.size} bytes, got {len(data)}")
        version, drone_id, step, ax, ay = _CONTROL.unpack(data)
        if version != WIRE_VERSION:
            raise WireError(f"control message version {version}, expected {WIRE_VERSION}")
        if not (math.isfinite(ax) and math.isfinite(ay)):
            raise WireError("control message with a non-finite acceleration")
        return cls(drone_id, step, (ax, ay))


@dataclass(frozen=True)
class NoiseReportMessage:
    """One drone's reported noise of the predictions it sends at one step.

    ``target_ids`` ``(n,)``; ``noise`` ``(n, 2, 2)`` m², symmetric.
    """

    drone_id: int
    step: int
    target_ids: tuple[int, ...]
    noise: np.ndarray

    def encode(self) -> bytes:
        """Pack to bytes (format in the module docstring)."""
        noise = np.clip(np.asarray(self.noise, dtype=float), -65504.0, 65504.0)  # f16 range
        parts = [_NOISE_HEAD.pack(WIRE_VERSION, self.drone_id, self.step, len(self.target_ids))]
        for target_id, r in zip(self.target_ids, noise, strict=True):
            parts.append(_NOISE_ITEM.pack(target_id, r[0, 0], r[0, 1], r[1, 1]))
        return b"".join(parts)

    @classmethod
    def decode(cls, data: bytes) -> NoiseReportMessage:
        """Unpack bytes made by :meth:`encode`; raises :class:`WireError` for anything else
        (wrong version or length, a target twice, a non-finite or negative variance)."""
        data = bytes(data)
        if len(data) < _NOISE_HEAD.size:
            raise WireError(f"noise report of {len(data)} bytes is shorter than its header")
        version, drone_id, step, count = _NOISE_HEAD.unpack_from(data)
        if version != WIRE_VERSION:
            raise WireError(f"noise report version {version}, expected {WIRE_VERSION}")
        if len(data) != _NOISE_HEAD.size + count * _NOISE_ITEM.size:
            raise WireError(f"noise report of {len(data)} bytes does not hold {count} items")
        items = list(_NOISE_ITEM.iter_unpack(data[_NOISE_HEAD.size :]))
        target_ids = tuple(item[0] for item in items)
        if len(set(target_ids)) != count:
            raise WireError("noise report names a target twice")
        values = np.array([item[1:] for item in items], dtype=float).reshape(count, 3)
        if not np.isfinite(values).all() or (values[:, [0, 2]] < 0).any():
            raise WireError("noise report with a non-finite or negative variance")
        noise = np.stack([values[:, [0, 1]], values[:, [1, 2]]], axis=1)  # (n, 2, 2)
        return cls(drone_id, step, target_ids, noise)


def split_uplink(data: bytes) -> tuple[bytes, bytes]:
    """A drone's per-step uplink as ``(prediction message, noise report)``: a drone that
    reports its noise sends the :class:`NoiseReportMessage` right after the
    :class:`PredictionMessage` in one payload (the report is ``b""`` when there is none).
    The prediction message's length is read from its header; a payload too short for one is
    returned whole, for :meth:`PredictionMessage.decode` to refuse."""
    data = bytes(data)
    if len(data) < _PRED_HEAD.size:
        return data, b""
    count = _PRED_HEAD.unpack_from(data)[4]
    end = _PRED_HEAD.size + count * _PRED_ITEM.size
    return data[:end], data[end:]


def raw_inputs_message(
    drone_id: int, step: int, odometry: np.ndarray, boxes: Iterable[Detection] = ()
) -> bytes:
    """What a drone of the centralized baseline sends each step besides a camera frame: its
    odometry vector ``(12,)`` and the ``boxes`` it detected (format in the module docstring)."""
    head = _RAW_HEAD.pack(drone_id, step, *np.asarray(odometry, dtype=np.float32))
    return head + b"".join(_RAW_BOX.pack(d.target_id, *d.box) for d in boxes)
