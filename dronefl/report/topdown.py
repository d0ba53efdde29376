"""Top-down picture of a run: field, rows or trees, vehicle and drone paths, camera footprints."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.collections import PatchCollection
from matplotlib.patches import Circle, Rectangle

from dronefl.config import Scenario
from dronefl.io import atomic_write_bytes
from dronefl.logs import GroundTruth
from dronefl.sim.camera import PinholeCamera
from dronefl.sim.environment import FarmEnvironment

#: One colour per target (tab10) and per drone (dark shades), shared by all DroneFL plots.
TARGET_COLOURS = plt.get_cmap("tab10").colors
DRONE_COLOURS = ("#1b1b1b", "#6a3d9a", "#b15928", "#33a02c", "#1f78b4", "#e31a1c")


def save_figure(fig: plt.Figure, path: Path, dpi: int = 120) -> Path:
    """Save ``fig`` as PNG to ``path`` atomically and close it."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return atomic_write_bytes(path, buffer.getvalue())


def draw_field(ax: plt.Axes, env: FarmEnvironment) -> None:
    """Field outline, headlands and crop rows (``crop_field``) or tree canopies (``orchard``)."""
    f = env.field
    ax.add_patch(Rectangle((0, 0), f.width, f.height, facecolor="#f3efe0", edgecolor="k", lw=1))
    for x0 in (0.0, f.width - f.headland):
        ax.add_patch(Rectangle((x0, 0), f.headland, f.height, facecolor="#e6dfc8", lw=0))
    if env.kind == "crop_field":
        for y in env.tree_row_y:
            ax.plot([f.headland, f.width - f.headland], [y, y], color="#9bbf6a", lw=0.6)
    elif env.kind == "orchard":
        canopies = [Circle((x, y), env.canopy_radius) for x, y in env.trees]
        ax.add_collection(PatchCollection(canopies, facecolor="#5f8f3a", alpha=0.45, lw=0))
    ax.set_xlim(-2, f.width + 2)
    ax.set_ylim(-2, f.height + 2)
    ax.set_aspect("equal")
    ax.set_xlabel("x (east), m")
    ax.set_ylabel("y (north), m")


def plot_topdown(
    scenario: Scenario,
    env: FarmEnvironment,
    camera: PinholeCamera,
    truth: GroundTruth,
    path: Path,
    detection_rates: dict[int, float] | None = None,
    n_footprints: int = 4,
) -> Path:
    """Write the top-down PNG of a recorded run to ``path``.

    Vehicle paths are solid (a triangle marks the start, a dot the end), drone paths dashed;
    each drone's camera footprint is drawn at ``n_footprints`` evenly spaced times.
    """
    fig, ax = plt.subplots(figsize=(10, 7.8))
    draw_field(ax, env)
    for j, tid in enumerate(truth.target_ids):
        xy = truth.target_position[:, j]
        colour = TARGET_COLOURS[j % len(TARGET_COLOURS)]
        ax.plot(xy[:, 0], xy[:, 1], color=colour, lw=1.6, label=f"target {tid}")
        ax.plot(*xy[0], marker=">", color=colour, ms=8)
        ax.plot(*xy[-1], marker="o", color=colour, ms=6)
    times = np.linspace(0, len(truth.t) - 1, n_footprints).astype(int)
    for i, did in enumerate(truth.drone_ids):
        xy = truth.drone_position[:, i]
        colour = DRONE_COLOURS[i % len(DRONE_COLOURS)]
        altitude = float(truth.drone_altitude[i])
        rate = "" if detection_rates is None else f", det. {detection_rates[int(did)]:.2f}"
        ax.plot(
            xy[:, 0],
            xy[:, 1],
            "--",
            color=colour,
            lw=1.2,
            label=f"drone {did} ({altitude:.0f} m{rate})",
        )
        hx, hy = camera.footprint_half_extent(altitude)
        for k in times:
            ax.add_patch(
                Rectangle(
                    (xy[k, 0] - hx, xy[k, 1] - hy),
                    2 * hx,
                    2 * hy,
                    fill=False,
                    edgecolor=colour,
                    lw=0.8,
                    alpha=0.7,
                )
            )
            ax.text(
                xy[k, 0] - hx + 0.8,
                xy[k, 1] + hy - 3.2,
                f"{truth.t[k]:.0f}s",
                color=colour,
                fontsize=6,
                clip_on=True,
            )
    duration = truth.t[-1] + (truth.t[1] - truth.t[0] if len(truth.t) > 1 else 0.0)
    ax.set_title(
        f"{scenario.name} in {env.kind}: {duration:.0f} s, "
        f"camera footprints (boxes) every {duration / max(n_footprints - 1, 1):.0f} s"
    )
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    return save_figure(fig, path)
