"""What the figures were measured on: CPU model, cores, library versions."""

from __future__ import annotations

import os
import platform
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

#: Libraries whose versions change the figures.
LIBRARIES: tuple[str, ...] = ("numpy", "torch", "onnxruntime", "flwr", "mujoco", "filterpy")


@dataclass(frozen=True)
class LoadAverage:
    """The 1, 5 and 15 min load averages (runnable processes) at the ``start`` and the ``end``
    of a benchmark run; None where the OS has none."""

    start: tuple[float, ...] | None
    end: tuple[float, ...] | None


@dataclass(frozen=True)
class MachineInfo:
    """What the figures were measured on: CPU model, cores visible, OS, Python, the versions of
    :data:`LIBRARIES` (None: not installed) and the load beside the run."""

    cpu_model: str
    cores_visible: int
    platform: str
    python: str
    versions: dict[str, str | None]
    load_average: LoadAverage


def cpu_model(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The ``model name`` line of ``cpuinfo`` (Linux), else what :mod:`platform` knows."""
    if cpuinfo.is_file():
        for line in cpuinfo.read_text(errors="replace").splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and value.strip():
                return value.strip()
    return platform.processor() or platform.machine()


def cores_visible() -> int:
    """CPU cores this process may run on (its affinity mask, not the machine's total)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def load_average() -> tuple[float, ...] | None:
    """The 1, 5 and 15 min load averages (runnable processes), None where the OS has none: on
    a shared machine they say how much else ran beside the benchmark."""
    try:
        return tuple(round(x, 2) for x in os.getloadavg())
    except (AttributeError, OSError):
        return None


def machine_info(load: LoadAverage) -> MachineInfo:
    """This machine, with the ``load`` measured beside the run."""
    versions: dict[str, str | None] = {}
    for name in LIBRARIES:
        try:
            versions[name] = version(name)
        except PackageNotFoundError:
            versions[name] = None
    return MachineInfo(
        cpu_model(), cores_visible(), platform.platform(), platform.python_version(), versions, load
    )
