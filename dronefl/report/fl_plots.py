"""Figures of the offline experiments: Fig. 5 (test MSE vs round), Fig. 4 (altitude) and the
centralized baseline's image model against the box model (crop field -> orchard)."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from dronefl.io import atomic_write_bytes  # noqa: E402
from dronefl.results.fl import Curve  # noqa: E402

#: Display names and colours, in the paper's legend order; other methods get the default cycle.
STYLE: dict[str, tuple[str, str]] = {
    "fedavg": ("FedAvg", "tab:blue"),
    "fedprox": ("FedProx", "tab:orange"),
    "fedper": ("FedPer", "tab:green"),
    "dronefl": ("DroneFL", "tab:red"),
    "centralized": ("Centralized", "black"),
    "centralized-small": ("Centralized (DroneFL's model)", "tab:gray"),
    "local": ("Local only", "tab:olive"),
    "dronefl-no-adain": ("DroneFL w/o AdaIN", "tab:purple"),
    "dronefl-absolute": ("DroneFL w/o relative pos.", "tab:brown"),
}


def plot_fig5(curves: dict[str, Curve], title: str, path: Path) -> Path:
    """Average test MSE across drones (m^2, log scale) vs global round for every method in
    ``curves`` (mean over seeds, the band +- one std)."""
    fig, ax = plt.subplots(figsize=(5.4, 3.8))
    for method, curve in curves.items():
        label, colour = STYLE.get(method, (method, None))
        _draw(ax, curve, label, colour)
    ax.set_yscale("log")
    ax.set_xlabel("global round")
    ax.set_ylabel("average test MSE (m$^2$)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    return _save(fig, path)


def plot_altitude(curves: dict[str, Curve], path: Path) -> Path:
    """Drone 1's test MSE (m^2, log scale) per round for each altitude setting (Fig. 4)."""
    fig, ax = plt.subplots(figsize=(5.4, 3.8))
    for label, curve in curves.items():
        _draw(ax, curve, label, None)
    ax.set_yscale("log")
    ax.set_xlabel("global round")
    ax.set_ylabel("drone 1 test MSE (m$^2$)")
    ax.set_title("Drone 2 at the same vs a different altitude")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    return _save(fig, path)


def plot_image_baseline(results: dict, path: Path) -> Path:
    """Left: each drone's prediction MSE (m^2, log scale) of the image model and of the box
    model, on the crop field's held-out steps and on the orchard run (``results.json`` of
    ``dronefl image-baseline``); middle: the same MSE over all drones by the target's distance
    from the drone (the image centre); right: the image model's training loss per epoch."""
    fig, (bars, offset, loss) = plt.subplots(1, 3, figsize=(13.0, 3.6))
    places = ("crop_field_held_out", "orchard")
    drones = sorted({d for scores in results["mse"].values() for d in scores[places[0]]}, key=int)
    x = np.arange(len(drones) * len(places))
    labels = [f"drone {d}\n{p.split('_')[0]}" for p in places for d in drones]
    for k, (model, colour) in enumerate((("image", "tab:red"), ("boxes", "black"))):
        values = [results["mse"][model][p][d] for p in places for d in drones]
        name = "image model (frames)" if model == "image" else "box model (detector boxes)"
        bars.bar(x + (k - 0.5) * 0.38, values, 0.38, color=colour, label=name)
    bars.set_xticks(x, labels, fontsize=7)
    bars.set_yscale("log")
    bars.set_ylabel("prediction MSE (m$^2$)")
    bars.set_title(f"{results['scenario']}: trained in the crop field")
    bars.legend(fontsize=7)
    bars.grid(True, axis="y", which="both", alpha=0.3)
    by_offset = results["mse_by_offset"]
    edges = by_offset["edges_m"]
    names = [f"{a:g}-{b:g}" for a, b in zip(edges[:-1], edges[1:], strict=True)]
    names.append(f">{edges[-1]:g}")
    for model, colour in (("image", "tab:red"), ("boxes", "black")):
        for place, style in (("crop_field_held_out", "--"), ("orchard", "-")):
            values = by_offset[model][place]["mse"]
            label = f"{'image' if model == 'image' else 'box'} model, {place.split('_')[0]}"
            offset.plot(names, values, style, marker="o", color=colour, label=label)
    offset.set_yscale("log")
    offset.set_xlabel("target's distance from the drone (m)")
    offset.set_ylabel("prediction MSE (m$^2$), all drones")
    offset.set_title("by distance from the image centre")
    offset.legend(fontsize=7)
    offset.grid(True, which="both", alpha=0.3)
    history = results["image_model"]["train_loss"]
    loss.plot(np.arange(1, len(history) + 1), history, color="tab:red")
    loss.set_yscale("log")
    loss.set_xlabel("epoch")
    loss.set_ylabel("training loss (m$^2$)")
    loss.set_title("image model, crop field")
    loss.grid(True, which="both", alpha=0.3)
    return _save(fig, path)


def _draw(ax: plt.Axes, curve: Curve, label: str, colour: str | None) -> None:
    rounds = np.arange(1, len(curve.mean) + 1)
    mean, std = np.asarray(curve.mean), np.asarray(curve.std)
    (line,) = ax.plot(rounds, mean, label=label, color=colour, lw=1.6)
    if std.any():
        low = np.maximum(mean - std, mean * 1e-3)  # the log axis needs positive values
        ax.fill_between(rounds, low, mean + std, color=line.get_color(), alpha=0.15, lw=0)


def _save(fig: plt.Figure, path: Path) -> Path:
    buffer = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buffer, format="png", dpi=150)
    plt.close(fig)
    return atomic_write_bytes(path, buffer.getvalue())
