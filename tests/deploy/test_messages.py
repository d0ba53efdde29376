"""Round trips and sizes of the deployment's own messages (sizes from the formats by hand)."""

import numpy as np
import pytest

from dronefl.deploy.messages import (
    LabelsMessage,
    SenseMessage,
    TelemetryMessage,
    decode_release,
    encode_release,
)
from dronefl.types import Detection, DroneState, Odometry
from dronefl.wire import WireError


def test_sense_message_round_trip_keeps_every_number():
    odometry = Odometry(1.4, np.arange(12, dtype=float) / 7)
    boxes = (Detection(2, (0.5, 0.25, 0.1, 0.05), 0.9), Detection(5, (0.1, 0.2, 0.3, 0.4), 0.6))
    data = SenseMessage(7, odometry, boxes).encode()
    # u32 + f64 + 12 f64 + u8 = 109 bytes, then 41 per box (u8 + 5 f64).
    assert len(data) == 109 + 2 * 41
    back = SenseMessage.decode(data)
    assert back.step == 7 and back.odometry.t == 1.4
    np.testing.assert_array_equal(back.odometry.vector, odometry.vector)
    assert back.detections == boxes


def test_telemetry_round_trip():
    drones = (
        DroneState(1, np.array([10.0, 20.0]), np.array([0.5, -0.5]), 30.0, np.array([0.1, 0.2])),
        DroneState(2, np.array([1.0, 2.0]), np.array([0.0, 0.0]), 20.0),
    )
    data = TelemetryMessage(3, 0.6, drones).encode()
    assert len(data) == 13 + 2 * 57  # u32 + f64 + u8; u8 + 7 f64 per drone
    back = TelemetryMessage.decode(data)
    assert back.step == 3 and back.t == 0.6
    for a, b in zip(back.drones, drones, strict=True):
        assert a.drone_id == b.drone_id and a.altitude == b.altitude
        np.testing.assert_array_equal(a.position, b.position)
        np.testing.assert_array_equal(a.velocity, b.velocity)
        np.testing.assert_array_equal(a.acceleration, b.acceleration)


def test_labels_travel_as_float32_with_nan_for_no_track():
    position = np.array([[[1.0, 2.0], [np.nan, np.nan]], [[1.5, 2.5], [3.0, 4.0]]])
    data = LabelsMessage(2, (1, 2), position).encode()
    assert len(data) == 7 + 2 + 2 * 2 * 2 * 4  # head u16 u32 u8, 2 ids, T x N x 2 f32
    back = LabelsMessage.decode(data)
    assert back.server_round == 2 and back.target_ids == (1, 2)
    np.testing.assert_array_equal(back.position, position)


def test_release_and_truncated_messages():
    assert decode_release(encode_release(599)) == 599
    data = SenseMessage(0, Odometry(0.0, np.zeros(12)), ()).encode()
    with pytest.raises(WireError, match="sense message"):
        SenseMessage.decode(data[:-1] + b"\x01")  # claims one box it does not hold
    with pytest.raises(WireError, match="release"):
        decode_release(b"\x00")
