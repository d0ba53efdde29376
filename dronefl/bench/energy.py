"""Energy: a real reading where the CPU exposes one (RAPL), otherwise an estimate.

*Reading*: the RAPL (Running Average Power Limit) package energy counters of Linux powercap,
``/sys/class/powercap/intel-rapl:N/energy_uj`` in uJ (AMD Zen CPUs appear under the same name),
read before and after ``calls`` calls of a workload. A reading covers the whole CPU package, so it
includes idle cores and any other process; recent kernels let only root read the counters.

*Estimate*, when there is no reading: energy = measured latency (s) x a stated device power (W),
always labelled ``kind = "estimate"`` with the power's source. The default powers are the
Raspberry Pi 5's implied by the paper's own Table II (energy / latency of the same row):
6.0 W while running YOLO (0.78 J per 0.13 s sample) and 8.0 W while training (14.11 J per
1.76 s epoch). The transformer row (0.11 J per 0.01 s) is left out: its latency has one
significant digit, so the power it implies (11 W) is uncertain by a factor of two; inference
uses the YOLO row's power for both models.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from time import perf_counter

from dronefl.serialize import omitted_when_none

#: Where Linux exposes RAPL.
POWERCAP = Path("/sys/class/powercap")


@dataclass(frozen=True)
class EnergyReading:
    """A RAPL reading (``kind`` ``"reading"``): ``joules`` (J) per call over ``calls`` calls,
    the package's ``mean_watts`` (W) meanwhile, and the counters it comes from."""

    kind: str
    joules: float
    calls: int
    mean_watts: float
    source: str


@dataclass(frozen=True)
class EnergyEstimate:
    """An estimate (``kind`` ``"estimate"``): ``joules`` (J) = ``latency_s`` (s) x ``watts``
    (W), the stated power of the device named in ``power_source``."""

    kind: str
    joules: float
    latency_s: float
    watts: float
    power_source: str


@dataclass(frozen=True)
class RaplStatus:
    """Whether RAPL can be read: the readable ``zones`` if it is, else the ``reason``."""

    available: bool
    reason: str | None = omitted_when_none()
    zones: tuple[str, ...] | None = omitted_when_none()


#: Measures the energy of ``calls`` calls of a function.
EnergyMeter = Callable[[Callable[[], object], int], EnergyReading]


@dataclass(frozen=True)
class PowerFigure:
    """A device power ``watts`` (W) and where the figure comes from."""

    watts: float
    source: str


RPI5_INFERENCE = PowerFigure(
    0.78 / 0.13,
    "Raspberry Pi 5 running YOLO inference, implied by the paper's Table II "
    "(0.78 J per 0.13 s sample)",
)
RPI5_TRAINING = PowerFigure(
    14.11 / 1.76,
    "Raspberry Pi 5 training the transformer, implied by the paper's Table II "
    "(14.11 J per 1.76 s epoch)",
)


def estimate(latency_s: float, power: PowerFigure) -> EnergyEstimate:
    """Energy estimate ``joules = latency_s x power.watts`` (J) of one call lasting
    ``latency_s`` s on a device drawing ``power``, labelled as an estimate."""
    if not (math.isfinite(latency_s) and latency_s > 0):
        raise ValueError(f"latency must be a positive number of seconds, got {latency_s}")
    return EnergyEstimate("estimate", latency_s * power.watts, latency_s, power.watts, power.source)


def rapl_zones(root: Path = POWERCAP) -> list[Path]:
    """The package-level RAPL zones under ``root`` (``intel-rapl:N``, not the sub-zones
    ``intel-rapl:N:M``, which the package counter already includes)."""
    return sorted(
        zone
        for zone in root.glob("intel-rapl:*")
        if zone.name.count(":") == 1 and (zone / "energy_uj").is_file()
    )


def rapl_status(root: Path = POWERCAP) -> RaplStatus:
    """Whether the RAPL zones under ``root`` can be read, or the ``reason`` why not."""
    zones = rapl_zones(root)
    if not zones:
        return RaplStatus(False, reason=f"not available: no RAPL zones under {root}")
    for zone in zones:
        try:
            int((zone / "energy_uj").read_text())
        except (OSError, ValueError) as exc:
            return RaplStatus(False, reason=f"not available: {zone}/energy_uj ({exc})")
    return RaplStatus(True, zones=tuple(str(zone) for zone in zones))


def rapl_meter(root: Path = POWERCAP) -> EnergyMeter | None:
    """An :data:`EnergyMeter` reading the RAPL package counters under ``root``, or ``None``
    when :func:`rapl_status` says they are not available."""
    if not rapl_status(root).available:
        return None
    zones = rapl_zones(root)
    ranges = [int((zone / "max_energy_range_uj").read_text()) for zone in zones]

    def read() -> list[int]:
        return [int((zone / "energy_uj").read_text()) for zone in zones]

    def measure(fn: Callable[[], object], calls: int) -> EnergyReading:
        before = read()
        started = perf_counter()
        for _ in range(calls):
            fn()
        wall = perf_counter() - started
        after = read()
        # A counter wraps to 0 after max_energy_range_uj.
        micro = sum(
            a - b if a >= b else a + r - b for a, b, r in zip(after, before, ranges, strict=True)
        )
        joules = micro / 1e6
        source = f"RAPL package energy ({', '.join(z.name for z in zones)}), whole package"
        return EnergyReading("reading", joules / calls, calls, joules / wall, source)

    return measure
