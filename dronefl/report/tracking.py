"""Plots of a closed-loop episode: trajectories, errors over time, an animation, Table I."""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Rectangle
from PIL import Image

from dronefl.config import Scenario
from dronefl.io import atomic_write_bytes
from dronefl.report.topdown import DRONE_COLOURS, TARGET_COLOURS, draw_field, save_figure
from dronefl.results.table1 import Table1Row
from dronefl.sim.camera import PinholeCamera
from dronefl.sim.environment import FarmEnvironment


def plot_episode(
    scenario: Scenario,
    env: FarmEnvironment,
    camera: PinholeCamera,
    log,
    out: Path,
    method: str,
    animate: bool = True,
    gif_frames: int = 100,
) -> None:
    """Write ``trajectories.png``, ``timeseries.png`` and (``animate``) ``episode.gif``."""
    _trajectories(scenario, env, log, out / "trajectories.png", method)
    _timeseries(scenario, log, out / "timeseries.png", method)
    if animate:
        _animation(scenario, env, camera, log, out / "episode.gif", method, gif_frames)


def _trajectories(scenario, env, log, path: Path, method: str) -> None:
    fig, ax = plt.subplots(figsize=(10, 7.8))
    draw_field(ax, env)
    for j, target_id in enumerate(scenario.target_ids):
        colour = TARGET_COLOURS[j % len(TARGET_COLOURS)]
        ax.plot(*log.target_position[:, j].T, color=colour, lw=1.6, label=f"target {target_id}")
        ax.plot(*log.track_position[:, j].T, ":", color=colour, lw=1.0)
    for i, drone in enumerate(scenario.drones):
        colour = DRONE_COLOURS[i % len(DRONE_COLOURS)]
        ax.plot(
            *log.drone_position[:, i].T,
            "--",
            color=colour,
            lw=1.1,
            label=f"drone {drone.id} ({drone.altitude:.0f} m)",
        )
    ax.plot([], [], ":", color="grey", label="fused track (EKF)")
    ax.set_title(f"{scenario.name}, {method}: true paths (solid), fused tracks (dotted)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    save_figure(fig, path)


def _timeseries(scenario, log, path: Path, method: str) -> None:
    t = log.t[:-1]
    column = {t_id: j for j, t_id in enumerate(scenario.target_ids)}
    errors = np.full((len(t), len(scenario.drones), len(scenario.targets)), np.nan)
    for i, drone in enumerate(scenario.drones):
        for target_id in drone.targets:
            j = column[target_id]
            diff = log.prediction[:, i, j] - log.target_position[1:, j]
            errors[:, i, j] = (diff**2).sum(axis=-1)
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    window = 25  # steps (5 s) of running mean
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # steps where nothing is predicted
        mean_error, mean_trace = np.nanmean(errors, axis=(1, 2)), np.nanmean(log.trace, axis=1)
    series = [
        (mean_error, "prediction error (m²)", True),
        (mean_trace, "uncertainty Tr P", True),
        (log.cost, "planner cost J", True),
    ]
    for ax, (values, label, log_scale) in zip(axes, series, strict=True):
        ax.plot(t, values, color="0.75", lw=0.6)
        ax.plot(t, _running_mean(values, window), color="C0", lw=1.4, label="5 s mean")
        for step in log.fl_steps:
            ax.axvline(log.t[step], color="C3", lw=0.8, ls="--")
        ax.set_ylabel(label)
        values = np.asarray(values, dtype=float)
        if log_scale and (np.isfinite(values) & (values > 0)).any():  # else: a linear axis
            ax.set_yscale("log")
    made = np.isfinite(errors)
    if (made & ~log.sent).any():  # drone.detected_only: the error of what reached the cloud too
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            sent_error = np.nanmean(np.where(log.sent, errors, np.nan), axis=(1, 2))
        axes[0].plot(
            t,
            _running_mean(sent_error, window),
            color="C2",
            lw=1.2,
            label="5 s mean, sent to the cloud",
        )
    if log.fl_steps:
        axes[0].plot([], [], color="C3", ls="--", label="FL round")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[0].set_title(f"{scenario.name}, {method}")
    axes[-1].set_xlabel("time (s)")
    save_figure(fig, path)


def _running_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Mean of the finite values in a centred window of ``window`` samples (shorter series:
    the window shrinks to the series)."""
    window = max(1, min(window, len(values)))
    ok = np.isfinite(values)
    filled = np.where(ok, values, 0.0)
    sums = np.convolve(filled, np.ones(window), mode="same")
    counts = np.convolve(ok.astype(float), np.ones(window), mode="same")
    with np.errstate(invalid="ignore", divide="ignore"):
        return sums / counts


def _animation(scenario, env, camera, log, path: Path, method: str, frames: int) -> None:
    """Top-down animation at 10 frames/s: vehicles, fused tracks, drones and their camera
    footprints. The field and the axes are drawn once; each frame redraws only the moving
    artists onto that background (blitting), so a 100-frame GIF costs about as much as one
    plot."""
    fig, ax = plt.subplots(figsize=(6.4, 5.0), dpi=70)
    draw_field(ax, env)
    steps = np.linspace(0, len(log.t) - 1, frames).astype(int)
    target_dots = ax.scatter(
        *log.target_position[0].T,
        s=30,
        zorder=4,
        c=[TARGET_COLOURS[j % 10] for j in range(len(scenario.targets))],
        animated=True,
    )
    track_dots = ax.scatter(
        *np.zeros((2, len(scenario.targets))),
        s=60,
        marker="x",
        color="k",
        lw=1.0,
        zorder=5,
        animated=True,
    )
    footprints = []
    for i, drone in enumerate(scenario.drones):
        hx, hy = camera.footprint_half_extent(drone.altitude)
        patch = Rectangle(
            (0, 0),
            2 * hx,
            2 * hy,
            fill=False,
            lw=1.2,
            edgecolor=DRONE_COLOURS[i % len(DRONE_COLOURS)],
            animated=True,
        )
        ax.add_patch(patch)
        footprints.append((patch, hx, hy))
    title = ax.set_title("", animated=True)
    canvas = fig.canvas
    canvas.draw()  # everything but the animated artists
    background = canvas.copy_from_bbox(fig.bbox)
    images = []
    for k in steps:
        target_dots.set_offsets(log.target_position[k])
        track = log.track_position[k]
        track_dots.set_offsets(np.where(np.isfinite(track), track, -100.0))
        for i, (patch, hx, hy) in enumerate(footprints):
            x, y = log.drone_position[k, i]
            patch.set_xy((x - hx, y - hy))
        fl = sum(1 for s in log.fl_steps if s <= k)
        title.set_text(f"{scenario.name} {method}  t = {log.t[k]:5.0f} s  FL rounds: {fl}")
        canvas.restore_region(background)
        for artist in (target_dots, track_dots, *(p for p, _, _ in footprints)):
            ax.draw_artist(artist)
        fig.draw_artist(title)
        images.append(Image.fromarray(np.asarray(canvas.buffer_rgba())).convert("RGB"))
    plt.close(fig)
    gif = io.BytesIO()
    images[0].save(gif, format="GIF", save_all=True, append_images=images[1:], duration=100, loop=0)
    atomic_write_bytes(path, gif.getvalue())


def plot_table1_bars(rows: list[Table1Row], path: Path) -> Path:
    """Bar chart of prediction error and tracking distance per scenario and method (mean ±
    std over seeds), every method that was run."""
    scenarios = list(dict.fromkeys(r.scenario for r in rows))
    methods = list(dict.fromkeys(r.method for r in rows))
    by_key = {(r.scenario, r.method): r for r in rows}
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    width = 0.8 / max(len(methods), 1)
    for ax, metric, label in zip(
        axes,
        ("prediction_error", "tracking_distance"),
        ("prediction error (m²)", "tracking distance (m²)"),
        strict=True,
    ):
        for k, method in enumerate(methods):
            cells = [by_key.get((s, method)) for s in scenarios]
            means = [c.mean[metric] if c else np.nan for c in cells]
            stds = [c.std[metric] if c else 0.0 for c in cells]
            x = np.arange(len(scenarios)) + (k - (len(methods) - 1) / 2) * width
            ax.bar(x, means, width, yerr=stds, capsize=3, label=method)
        ax.set_xticks(np.arange(len(scenarios)), scenarios)
        ax.set_ylabel(label)
        ax.set_yscale("log")
    handles, names = axes[0].get_legend_handles_labels()  # below the axes: never over a bar
    fig.legend(handles, names, loc="lower center", ncol=min(len(methods), 5), fontsize=8)
    fig.subplots_adjust(bottom=0.2)
    return save_figure(fig, path)
