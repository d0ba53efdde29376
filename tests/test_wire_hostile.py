"""Hostile bytes (Hypothesis): random, truncated, oversized and valid-header-random-body
messages make every wire decoder raise WireError (never another exception); random valid
messages round-trip."""

import struct

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from dronefl.wire import WIRE_VERSION, ControlMessage, PredictionMessage, WireError

DECODERS = (PredictionMessage.decode, ControlMessage.decode)
#: Examples per property; the counts in the README are these times the number of properties.
EXAMPLES = 200
PROPERTY = settings(max_examples=EXAMPLES, deadline=None, derandomize=True, database=None)


def decodes_or_rejects(decode, data: bytes):
    """A decoder either returns a message or raises WireError; anything else fails."""
    try:
        return decode(data)
    except WireError:
        return None


@st.composite
def predictions(draw):
    n = draw(st.integers(0, 6))
    horizon = draw(st.integers(1, 5))
    target_ids = tuple(draw(st.lists(st.integers(0, 255), min_size=n, max_size=n, unique=True)))
    centimetres = draw(
        st.lists(st.integers(-32767, 32767), min_size=n * horizon * 2, max_size=n * horizon * 2)
    )
    positions = np.array(centimetres, dtype=float).reshape(n, horizon, 2) / 100.0
    return PredictionMessage(
        draw(st.integers(0, 255)), draw(st.integers(0, 2**32 - 1)), target_ids, positions
    )


controls = st.builds(
    ControlMessage,
    st.integers(0, 255),
    st.integers(0, 2**32 - 1),
    st.tuples(*[st.floats(width=32, allow_nan=False, allow_infinity=False)] * 2),
)


@PROPERTY
@given(predictions())
def test_valid_predictions_round_trip(message):
    back = PredictionMessage.decode(message.encode())
    assert (back.drone_id, back.step, back.target_ids) == (
        message.drone_id,
        message.step,
        message.target_ids,
    )
    assert np.array_equal(back.positions, message.positions)  # whole centimetres: exact


@PROPERTY
@given(controls)
def test_valid_controls_round_trip(message):
    assert ControlMessage.decode(message.encode()) == message


@PROPERTY
@given(st.binary(max_size=200))
def test_random_bytes_are_rejected_or_decoded_never_crash(data):
    for decode in DECODERS:
        decodes_or_rejects(decode, data)


@PROPERTY
@given(predictions(), st.data())
def test_truncated_predictions_are_rejected(message, data):
    encoded = message.encode()
    cut = data.draw(st.integers(0, len(encoded) - 1))
    try:
        PredictionMessage.decode(encoded[:cut])
    except WireError:
        return
    raise AssertionError(f"{cut} of {len(encoded)} bytes decoded")


@PROPERTY
@given(controls, st.data())
def test_truncated_and_oversized_controls_are_rejected(message, data):
    encoded = message.encode()
    cut = data.draw(st.integers(0, len(encoded) - 1))
    extra = data.draw(st.binary(min_size=1, max_size=64))
    for bad in (encoded[:cut], encoded + extra):
        try:
            ControlMessage.decode(bad)
        except WireError:
            continue
        raise AssertionError(f"{len(bad)} bytes decoded")


@PROPERTY
@given(predictions(), st.binary(min_size=1, max_size=4096))
def test_oversized_predictions_are_rejected(message, extra):
    try:
        PredictionMessage.decode(message.encode() + extra)
    except WireError:
        return
    raise AssertionError("a message with trailing bytes decoded")


@PROPERTY
@given(
    st.integers(0, 255),
    st.integers(0, 2**32 - 1),
    st.integers(0, 255),
    st.integers(0, 2**16 - 1),
    st.binary(max_size=600),
)
def test_valid_prediction_header_with_a_random_body(drone, step, horizon, count, body):
    data = struct.pack("<BBIBH", WIRE_VERSION, drone, step, horizon, count) + body
    message = decodes_or_rejects(PredictionMessage.decode, data)
    if message is not None:  # then it is a message encode() could have made
        assert message.encode() == data


@PROPERTY
@given(st.integers(0, 255), st.integers(0, 2**32 - 1), st.binary(min_size=8, max_size=8))
def test_valid_control_header_with_a_random_body(drone, step, body):
    data = struct.pack("<BBI", WIRE_VERSION, drone, step) + body
    message = decodes_or_rejects(ControlMessage.decode, data)
    if message is not None:
        assert all(np.isfinite(message.acceleration)) and message.encode() == data


@PROPERTY
@given(st.integers(0, 255).filter(lambda v: v != WIRE_VERSION), st.binary(max_size=100))
def test_another_version_is_rejected(version, rest):
    for decode in DECODERS:
        try:
            decode(bytes([version]) + rest)
        except WireError:
            continue
        raise AssertionError("a message of another version decoded")
