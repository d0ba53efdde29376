"""Byte accounting: rates per drone, direction and kind, by hand."""

import pytest

from dronefl.accounting import ByteCounter


def test_byte_counter_rates_and_breakdown():
    counter = ByteCounter()
    for _ in range(50):  # 10 s at 5 Hz
        counter.add(1, "up", "predictions", 19)
        counter.add(1, "down", "control", 14)
    counter.add(2, "up", "weights", 5000)
    rates = counter.rates(10.0)
    assert rates.kb_per_s(1) == pytest.approx((19 + 14) * 5 / 1000)
    assert rates.kb_per_s(1, "up", "predictions") == pytest.approx(0.095)
    assert rates.kb_per_s(2) == pytest.approx(0.5)
    assert rates.mean_per_drone() == pytest.approx((0.165 + 0.5) / 2)
    assert rates.kinds() == (("down", "control"), ("up", "predictions"), ("up", "weights"))
    with pytest.raises(ValueError, match="direction"):
        counter.add(1, "sideways", "x", 1)
