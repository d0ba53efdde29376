"""What the figures were measured on: CPU model, cores, library versions."""

from __future__ import annotations

import os
import platform
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

#: Libraries whose versions change the figures.
LIBRARIES: tuple[str, ...] = ("numpy", "torch", "onnxruntime", "flwr", "mujoco", "filterpy")


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


def load_average() -> list[float] | None:
    """The 1, 5 and 15 min load averages (runnable processes), None where the OS has none: on
    a shared machine they say how much else ran beside the benchmark."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except (AttributeError, OSError):
        return None


def machine_info() -> dict:
    """CPU model, cores visible, OS, Python and :data:`LIBRARIES` versions (None: missing)."""
    versions = {}
    for name in LIBRARIES:
        try:
            versions[name] = version(name)
        except PackageNotFoundError:
            versions[name] = None
    return {
        "cpu_model": cpu_model(),
        "cores_visible": cores_visible(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "versions": versions,
    }
