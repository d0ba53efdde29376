"""The vision path's figures (docs/vision.md): rendered camera frames with the YOLO
detections drawn on them, and the detector's measured quality against altitude."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from PIL import Image, ImageDraw

from dronefl.config import load_scenario
from dronefl.io import atomic_write_bytes
from dronefl.perception.dataset import DATASET_ENVIRONMENTS
from dronefl.perception.projection import vehicle_boxes
from dronefl.perception.quality import DetectorReport
from dronefl.perception.render import SceneRenderer
from dronefl.perception.yolo import YoloDetector
from dronefl.report.topdown import save_figure
from dronefl.sim.pilot import PilotController
from dronefl.sim.world import World
from dronefl.types import CameraView, Detection

#: Simulated seconds of Case 3 under the scripted pilot before the frames are taken.
SETTLE_S = 20.0


def draw_detections(
    image: np.ndarray, detections: tuple[Detection, ...], truth: np.ndarray | None = None
) -> Image.Image:
    """``image`` ``(H, W, 3)`` uint8 with the detections (white box, ``id conf`` label) and,
    if given, the projected true boxes ``(N, 4)`` normalised (thin black)."""
    frame = Image.fromarray(image)
    draw = ImageDraw.Draw(frame)
    h, w = image.shape[:2]

    def corners(box: np.ndarray) -> tuple[float, float, float, float]:
        cx, cy, bw, bh = box[0] * w, box[1] * h, box[2] * w, box[3] * h
        return cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2

    for box in truth if truth is not None else ():
        draw.rectangle(corners(box), outline=(0, 0, 0), width=1)
    for d in detections:
        x1, y1, x2, y2 = corners(np.asarray(d.box))
        draw.rectangle((x1 - 2, y1 - 2, x2 + 2, y2 + 2), outline=(255, 255, 255), width=2)
        label = f"{d.target_id} {d.confidence:.2f}"
        draw.rectangle((x1 - 2, y1 - 14, x1 + 6 * len(label), y1 - 2), fill=(255, 255, 255))
        draw.text((x1, y1 - 14), label, fill=(0, 0, 0))
    return frame


def detection_panel(
    world: World, renderer: SceneRenderer, detector: YoloDetector, drone_ids: tuple[int, ...]
) -> Image.Image:
    """Side-by-side frames of ``drone_ids`` with detections and projected truth, captioned."""
    views = {v.drone_id: v for v in world.camera_views()}
    tiles = []
    for drone_id in drone_ids:
        view = views[drone_id]
        image = renderer.render_view(view)
        detections = detector.detect(
            CameraView(view.drone_id, view.t, view.camera_position, view.yaw, view.targets, image)
        )
        positions = np.array([t.position for t in view.targets])
        headings = np.array([t.heading for t in view.targets])
        truth, inside = vehicle_boxes(
            world.camera, world.scenario.vehicle, view.camera_position, view.yaw, positions,
            headings,
        )  # fmt: skip
        tile = draw_detections(image, detections, truth[inside > 0])
        caption = ImageDraw.Draw(tile)
        text = (
            f"{world.environment.kind}, drone {drone_id} at {view.camera_position[2]:.0f} m: "
            f"{len(detections)} detections"
        )
        caption.rectangle((0, 0, 6 * len(text) + 8, 16), fill=(0, 0, 0))
        caption.text((4, 2), text, fill=(255, 255, 255))
        tiles.append(tile)
    panel = Image.new("RGB", (sum(t.width for t in tiles) + 8 * (len(tiles) - 1), tiles[0].height))
    x = 0
    for tile in tiles:
        panel.paste(tile, (x, 0))
        x += tile.width + 8
    return panel


def plot_quality(report: DetectorReport, path: Path) -> Path:
    """Miss rate and centre error of the YOLO detector against altitude, per environment."""
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for env, result in report.environments.items():
        rows = result.bins
        names = [r.altitude_m for r in rows]
        axes[0].plot(names, [r.miss_rate for r in rows], "o-", label=env)
        axes[1].plot(names, [r.center_rms_px for r in rows], "o-", label=env)
    axes[0].set_ylabel("miss rate (IoU < 0.5 or not found)")
    axes[1].set_ylabel("centre error RMS, px (640 px frame)")
    for ax in axes:
        ax.set_xlabel("altitude bin, m")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    return save_figure(fig, path)


def write_detector_figures(out: Path, weights: Path | None, eval_json: Path) -> list[Path]:
    """Frames of Case 3 (drones 1 at 60 m and 4 at 20 m, after ``SETTLE_S`` s of the scripted
    pilot) in both environments with detections, plus the quality plot if ``eval_json``
    exists. Returns the written PNG paths."""
    scenario = load_scenario("case3")
    detector = YoloDetector(weights, target_ids=scenario.target_ids)
    written = []
    for env in DATASET_ENVIRONMENTS:
        world = World(scenario, environment=env, seed=0)
        pilot = PilotController()
        for _ in range(round(SETTLE_S / world.dt)):
            world.step(pilot.control(world))
        renderer = SceneRenderer.from_scenario(scenario, world.environment)
        panel = detection_panel(world, renderer, detector, (1, 4))
        renderer.close()
        buffer = io.BytesIO()
        panel.save(buffer, format="png")
        written.append(atomic_write_bytes(out / f"detector_{env}.png", buffer.getvalue()))
    if eval_json.is_file():
        report = DetectorReport.load(eval_json)
        written.append(plot_quality(report, out / "detector_quality.png"))
    return written
