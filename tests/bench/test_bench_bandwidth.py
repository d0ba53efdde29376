"""Communication figures by hand: the centralized JPEG uplink and DroneFL's bytes."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from dronefl.accounting import ByteCounter
from dronefl.bench.bandwidth import ODOMETRY_BYTES, centralized_uplink, dronefl_comm
from dronefl.bench.vision import Frame
from dronefl.perception.uplink import DEFAULT_JPEG_QUALITY, encode_jpeg


def _frame(drone_id: int, shade: int) -> Frame:
    image = np.full((64, 64, 3), shade, dtype=np.uint8)
    image[16:32, 16:40] = (200, 30, 30)
    return Frame(drone_id, 0.0, image, render_seconds=0.01)


def test_centralized_uplink_is_message_bytes_times_rate_per_drone():
    frames = {
        "crop_field": [_frame(1, 90), _frame(1, 100), _frame(2, 90)],
        "orchard": [_frame(1, 60), _frame(2, 70)],
    }

    uplink = centralized_uplink(frames, rate_hz=5.0)

    sizes = [len(encode_jpeg(f.image, DEFAULT_JPEG_QUALITY)) for f in frames["crop_field"][:2]]
    drone_1 = ODOMETRY_BYTES + np.mean(sizes)
    crop = uplink.per_environment["crop_field"]
    assert crop.drones[1] == pytest.approx(drone_1 * 5.0 / 1000)
    assert crop.kb_per_s == pytest.approx(np.mean(list(crop.drones.values())))
    assert uplink.environment == "orchard"  # the deployment environment is the headline
    assert uplink.kb_per_s == uplink.per_environment["orchard"].kb_per_s


def _metrics(rounds: int) -> SimpleNamespace:
    # Two drones over 600 s; each round moves 60 kB down and 60 kB up per drone.
    counter = ByteCounter()
    for drone in (1, 2):
        counter.add(drone, "up", "predictions", 120_000)  # 0.2 KB/s
        counter.add(drone, "down", "control", 42_000)  # 0.07 KB/s
        if rounds:
            counter.add(drone, "up", "weights", 60_000 * rounds)
            counter.add(drone, "down", "weights", 60_000 * rounds)
    return SimpleNamespace(
        sim_seconds=600.0, fl_rounds=[None] * rounds, communication=counter.rates(600.0)
    )


def test_dronefl_comm_rescales_the_rounds_to_one_per_period():
    comm = dronefl_comm(_metrics(rounds=5), fl_period=100.0, weights_dtype="float16")

    assert comm.kb_per_s == pytest.approx(0.27 + 2 * 0.5)  # 5 rounds x 120 kB in 600 s
    assert comm.weights_kb_per_round == pytest.approx(120.0)
    assert comm.at_fl_period == pytest.approx(0.27 + 1.2)  # one 120 kB round per 100 s
    assert comm.by_type["up:predictions"] == pytest.approx(0.2)
    assert comm.what.startswith("DroneFL with fp16 weights") and comm.weights_dtype == "float16"


def test_dronefl_comm_without_a_round_has_no_per_period_figure():
    comm = dronefl_comm(_metrics(rounds=0), fl_period=100.0, weights_dtype="float32")
    assert math.isnan(comm.at_fl_period) and comm.kb_per_s == pytest.approx(0.27)
