"""Timing helpers: the latency figure, the reference ratio, interleaved calls."""

import numpy as np
import pytest

from dronefl.bench.timing import latency, time_calls, time_interleaved, with_reference


def test_latency_reports_median_and_p95_in_the_unit():
    seconds = np.array([1.0, 2.0, 3.0, 4.0, 5.0]) * 1e-3

    figure = latency("five calls", seconds, "ms", threads=1)

    assert figure.median == pytest.approx(3.0)
    assert figure.p95 == pytest.approx(4.8)  # 4 + 0.8 x (5 - 4), linear interpolation
    assert (figure.unit, figure.samples, figure.threads) == ("ms", 5, 1)
    assert figure.reference is None and figure.ratio is None


@pytest.mark.parametrize("seconds", [[], [1.0, np.nan]])
def test_latency_rejects_empty_or_non_finite_samples(seconds):
    with pytest.raises(ValueError, match="finite samples"):
        latency("bad", np.array(seconds), "s", 1)


def test_ratio_is_reference_over_ours():
    ours = latency("ours", np.full(3, 2e-3), "ms", 1)
    reference = latency("stock", np.full(3, 5e-3), "ms", 1)

    figure = with_reference(ours, reference)

    assert figure.ratio == pytest.approx(2.5)  # 5 ms / 2 ms
    assert figure.reference == reference and figure.median == pytest.approx(2.0)
    with pytest.raises(ValueError, match="unit"):
        with_reference(ours, latency("stock", np.full(3, 5e-3), "s", 1))


def test_interleaved_calls_take_turns_round_by_round():
    calls = []
    fns = {"a": lambda: calls.append("a"), "b": lambda: calls.append("b")}

    seconds = time_interleaved(fns, calls=2, rounds=3, warmup=1)

    assert calls == ["a", "b"] + ["a", "a", "b", "b"] * 3
    assert {k: v.shape for k, v in seconds.items()} == {"a": (6,), "b": (6,)}
    assert all((v >= 0).all() for v in seconds.values())


def test_time_calls_counts_warmup_apart():
    count = []
    seconds = time_calls(lambda: count.append(1), calls=4, warmup=2)
    assert len(count) == 6 and seconds.shape == (4,)
    with pytest.raises(ValueError):
        time_calls(lambda: None, calls=0)
