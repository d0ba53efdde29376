"""Fitting the projection noise model to detector outcomes recovers known parameters."""

import numpy as np
import pytest

from dronefl.perception.evaluation import VehicleOutcome, fit_projection_noise, iou_xywh


def synthetic_outcomes(n: int, seed: int) -> list[VehicleOutcome]:
    """Outcomes of a detector with P(miss) = 0.02 + 0.004 * max(0, r - 40), centre error
    N(0, 2^2) px, size error N(0, 0.05^2), and nothing found below visible fraction 0.4."""
    rng = np.random.default_rng(seed)
    outcomes = []
    for _ in range(n):
        slant = rng.uniform(15.0, 90.0)
        visible = 1.0 if rng.random() < 0.8 else rng.uniform(0.0, 0.4)
        p_miss = 0.02 + 0.004 * max(0.0, slant - 40.0)
        found = visible >= 0.4 and rng.random() >= p_miss
        outcomes.append(
            VehicleOutcome(
                "crop_field", slant, slant, visible, visible >= 0.5, found,
                tuple(rng.normal(0.0, 2.0, 2)) if found else None,
                tuple(rng.normal(0.0, 0.05, 2)) if found else None,
            )
        )  # fmt: skip
    return outcomes


def test_fit_recovers_known_noise() -> None:
    fitted = fit_projection_noise(synthetic_outcomes(20000, seed=0))
    assert fitted.center_px == pytest.approx(2.0, rel=0.05)
    assert fitted.size_frac == pytest.approx(0.05, rel=0.05)
    assert fitted.min_visible == pytest.approx(0.4, abs=0.05)
    assert fitted.miss_base == pytest.approx(0.02, abs=0.01)
    assert fitted.miss_per_m == pytest.approx(0.004, rel=0.2)
    assert fitted.miss_range0 == pytest.approx(40.0, abs=5.0)


def test_fit_without_any_detection_raises() -> None:
    nothing = [VehicleOutcome("orchard", 30.0, 30.0, 1.0, True, False, None, None)]
    with pytest.raises(ValueError, match="found no vehicle"):
        fit_projection_noise(nothing)


def test_iou_by_hand() -> None:
    a = np.array([0.5, 0.5, 0.2, 0.2])
    assert iou_xywh(a, a) == pytest.approx(1.0)
    assert iou_xywh(a, a + [0.1, 0.0, 0.0, 0.0]) == pytest.approx(0.02 / 0.06)
    assert iou_xywh(a, a + [0.5, 0.0, 0.0, 0.0]) == 0.0
