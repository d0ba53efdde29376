"""Figures of the offline FL experiment: Fig. 5 (test MSE vs round) and Fig. 4 (altitude)."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from dronefl.io import atomic_write_bytes  # noqa: E402

#: Display names and colours, in the paper's legend order.
STYLE: dict[str, tuple[str, str]] = {
    "fedavg": ("FedAvg", "tab:blue"),
    "fedprox": ("FedProx", "tab:orange"),
    "fedper": ("FedPer", "tab:green"),
    "dronefl": ("DroneFL", "tab:red"),
    "centralized": ("Centralized", "black"),
    "dronefl-no-adain": ("DroneFL w/o AdaIN", "tab:purple"),
    "dronefl-absolute": ("DroneFL w/o relative pos.", "tab:brown"),
}


def plot_fig5(results: dict, path: Path, methods: tuple[str, ...]) -> Path:
    """Average test MSE across drones (m^2, log scale) vs global round for ``methods``."""
    fig, ax = plt.subplots(figsize=(5.0, 3.6))
    for method in methods:
        block = results["methods"].get(method)
        if block is None:
            continue
        label, colour = STYLE.get(method, (method, None))
        curve = block["mean_test_mse"]
        ax.plot(range(1, len(curve) + 1), curve, label=label, color=colour, lw=1.6)
    ax.set_yscale("log")
    ax.set_xlabel("global round")
    ax.set_ylabel("average test MSE (m$^2$)")
    ax.set_title(f"Case {results['case']} ({results['scenario']})")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


def plot_altitude(study: dict, path: Path) -> Path:
    """Drone 1's test MSE (m^2, log scale) per round for each altitude setting (Fig. 4)."""
    fig, ax = plt.subplots(figsize=(5.0, 3.6))
    for label, curve in study["curves"].items():
        values = curve["drone_1_test_mse"]
        ax.plot(range(1, len(values) + 1), values, label=label, lw=1.6)
    ax.set_yscale("log")
    ax.set_xlabel("global round")
    ax.set_ylabel("drone 1 test MSE (m$^2$)")
    ax.set_title("Drone 2 at the same vs a different altitude")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, path)


def _save(fig: plt.Figure, path: Path) -> Path:
    buffer = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buffer, format="png", dpi=150)
    plt.close(fig)
    return atomic_write_bytes(path, buffer.getvalue())
