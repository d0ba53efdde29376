"""Energy: labelled estimates (latency x stated power) and RAPL readings from a fake sysfs."""

import math

import pytest

from dronefl.bench.energy import (
    RPI5_INFERENCE,
    RPI5_TRAINING,
    PowerFigure,
    estimate,
    rapl_meter,
    rapl_status,
    rapl_zones,
)


def test_estimate_is_latency_times_stated_power():
    power = PowerFigure(6.0, "a stated device")

    energy = estimate(0.25, power)

    assert energy.joules == pytest.approx(1.5)
    assert energy.kind == "estimate"
    assert energy.power_source == "a stated device"


def test_default_powers_are_the_papers_energy_over_latency():
    # Paper Table II, DroneFL on a Raspberry Pi 5: YOLO 0.78 J / 0.13 s, an epoch 14.11 J / 1.76 s.
    assert RPI5_INFERENCE.watts == pytest.approx(6.0)
    assert RPI5_TRAINING.watts == pytest.approx(8.017, abs=1e-3)
    assert "Table II" in RPI5_INFERENCE.source and "Table II" in RPI5_TRAINING.source


@pytest.mark.parametrize("latency_s", [0.0, -1.0, math.nan])
def test_estimate_rejects_a_non_positive_latency(latency_s):
    with pytest.raises(ValueError, match="positive"):
        estimate(latency_s, RPI5_INFERENCE)


def test_no_rapl_zones_means_no_reading(tmp_path):
    status = rapl_status(tmp_path)
    assert status.available is False and "not available" in status.reason
    assert rapl_meter(tmp_path) is None


def _zone(root, name, energy_uj, range_uj=1_000_000):
    zone = root / name
    zone.mkdir()
    (zone / "energy_uj").write_text(f"{energy_uj}\n")
    (zone / "max_energy_range_uj").write_text(f"{range_uj}\n")
    return zone


@pytest.mark.parametrize("start_uj", [100, 999_500])  # the second wraps past the range
def test_rapl_reading_is_the_package_counter_difference_per_call(tmp_path, start_uj):
    package = _zone(tmp_path, "intel-rapl:0", start_uj)
    _zone(tmp_path, "intel-rapl:0:0", 0)  # a sub-zone: already inside the package counter
    counter = package / "energy_uj"

    def workload():  # each call costs 250 uJ
        value = (int(counter.read_text()) + 250) % 1_000_000
        counter.write_text(str(value))

    meter = rapl_meter(tmp_path)
    reading = meter(workload, 4)

    assert [z.name for z in rapl_zones(tmp_path)] == ["intel-rapl:0"]
    assert rapl_status(tmp_path).zones == (str(package),)
    assert reading.kind == "reading"
    assert reading.joules == pytest.approx(250e-6)
    assert reading.calls == 4
