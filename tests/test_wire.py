"""Per-step wire formats: sizes from the documented layout, exact round trips, bad bytes."""

import numpy as np
import pytest

from dronefl.wire import (
    MAX_COORDINATE,
    ControlMessage,
    NoiseReportMessage,
    PredictionMessage,
    WireError,
)


def test_prediction_message_size_and_round_trip():
    positions = np.array([[[12.5, 40.25]], [[80.0, 3.5]], [[1.0, 2.0]]])  # (3 targets, L_f 1, 2)
    message = PredictionMessage(drone_id=2, step=1234, target_ids=(1, 4, 6), positions=positions)
    data = message.encode()
    assert len(data) == 9 + 6 * 3
    back = PredictionMessage.decode(data)
    assert (back.drone_id, back.step, back.target_ids) == (2, 1234, (1, 4, 6))
    assert np.array_equal(back.positions, positions)  # whole centimetres travel exactly


def test_prediction_positions_are_rounded_to_centimetres_and_saturate():
    positions = np.array([[[12.3456, -0.004]], [[500.0, -1000.0]]])
    back = PredictionMessage.decode(PredictionMessage(1, 1, (1, 2), positions).encode())
    np.testing.assert_allclose(back.positions[0, 0], [12.35, 0.0], atol=1e-12)
    np.testing.assert_allclose(back.positions[1, 0], [MAX_COORDINATE, -MAX_COORDINATE])


def test_prediction_message_with_a_longer_horizon_and_none():
    positions = np.arange(2 * 5 * 2, dtype=float).reshape(2, 5, 2)
    data = PredictionMessage(1, 7, (3, 5), positions).encode()
    assert len(data) == 9 + 6 * 2 * 5
    assert np.array_equal(PredictionMessage.decode(data).positions, positions)
    empty = PredictionMessage(1, 8, (), np.zeros((0, 1, 2))).encode()
    assert len(empty) == 9 and PredictionMessage.decode(empty).target_ids == ()
    # A drone that sees none of its targets still says which horizon it predicts.
    assert PredictionMessage.decode(empty).positions.shape == (0, 1, 2)


def test_control_message_round_trip():
    data = ControlMessage(3, 99, (0.5, -1.25)).encode()
    assert len(data) == 14
    assert ControlMessage.decode(data) == ControlMessage(3, 99, (0.5, -1.25))


@pytest.mark.parametrize(
    "data, match",
    [
        (b"\x01\x02", "shorter than its header"),
        (b"\x09" + bytes(8), "version 9"),
        (PredictionMessage(1, 1, (1,), np.zeros((1, 1, 2))).encode()[:-3], "does not hold"),
    ],
)
def test_damaged_prediction_messages_are_rejected(data, match):
    with pytest.raises(WireError, match=match):
        PredictionMessage.decode(data)


def test_noise_report_size_round_trip_and_damage():
    noise = np.array([[[0.25, 0.01], [0.01, 0.5]], [[2.0, -0.5], [-0.5, 3.0]]])  # (2, 2, 2) m^2
    data = NoiseReportMessage(3, 77, (2, 5), noise).encode()
    assert len(data) == 7 + 7 * 2
    back = NoiseReportMessage.decode(data)
    assert (back.drone_id, back.step, back.target_ids) == (3, 77, (2, 5))
    np.testing.assert_allclose(back.noise, noise, rtol=1e-3)  # half floats: 3 digits
    assert np.array_equal(back.noise, back.noise.transpose(0, 2, 1))
    huge = NoiseReportMessage(1, 1, (1,), np.eye(2)[None] * 1e9).encode()
    assert NoiseReportMessage.decode(huge).noise[0, 0, 0] == 65504.0  # saturated, not inf
    assert len(NoiseReportMessage(1, 1, (), np.zeros((0, 2, 2))).encode()) == 7
    with pytest.raises(WireError, match="does not hold"):
        NoiseReportMessage.decode(data[:-1])
    with pytest.raises(WireError, match="negative"):
        NoiseReportMessage.decode(NoiseReportMessage(1, 1, (1,), -np.eye(2)[None]).encode())
