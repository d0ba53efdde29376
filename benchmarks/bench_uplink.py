"""Centralized-baseline uplink: JPEG camera frames per drone, their cost and effect on detection.

Run: ``.venv/bin/python benchmarks/bench_uplink.py [--seconds 120] [--every 5]``.

Frames are Case 3 camera views (drones 1-4 at 60, 40, 30, 20 m, the scripted pilot flying them)
in ``crop_field`` and ``orchard``: every ``--every``-th step of ``--seconds`` s, all four drones,
rendered at 640 x 640. For each JPEG quality (Pillow, 4:2:0 chroma, as the detector's training
frames) it prints per environment and altitude:

* mean and p95 bytes per frame (KB, 1 KB = 1000 B) and the uplink per drone at 5 Hz (KB/s);
* encode + decode time per frame (ms, median);
* ``kept``: the share of the YOLO detections on the raw frame that are still reported after the
  JPEG round trip (same target id, IoU >= 0.5 with the raw-frame box), ``IoU``: the mean IoU of
  the kept boxes with their raw-frame boxes, and ``new``: detections per frame the JPEG frame
  adds (ids absent from the raw frame's detections).

The paper's centralized baseline sends raw images, 2.46 MB/s per drone; ``/paper`` is that
uplink divided by the JPEG one.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field

import numpy as np

from dronefl.config import load_scenario
from dronefl.perception.evaluation import iou_xywh
from dronefl.perception.render import SceneRenderer
from dronefl.perception.uplink import decode_jpeg, encode_jpeg
from dronefl.perception.yolo import YoloDetector
from dronefl.progress import progress_bar
from dronefl.sim.pilot import PilotController
from dronefl.sim.world import World
from dronefl.types import Detection

QUALITIES = (50, 75, 90, 95)
#: The paper's centralized baseline: raw images, MB/s per drone.
PAPER_RAW_MB_S = 2.46


@dataclass
class Tally:
    """Per (environment, altitude, quality): frame sizes (B), codec times (s) and matches."""

    sizes: list[int] = field(default_factory=list)
    codec_s: list[float] = field(default_factory=list)
    raw_detections: int = 0
    kept_iou: list[float] = field(default_factory=list)
    new: int = 0


def compare(raw: tuple[Detection, ...], coded: tuple[Detection, ...]) -> tuple[list[float], int]:
    """IoUs of the raw detections kept in ``coded`` (same id, IoU >= 0.5) and the number of ids
    only ``coded`` has."""
    boxes = {d.target_id: np.array(d.box) for d in coded}
    ious = [iou_xywh(np.array(d.box), boxes[d.target_id]) for d in raw if d.target_id in boxes]
    return [v for v in ious if v >= 0.5], len(boxes.keys() - {d.target_id for d in raw})


def render_frames(env: str, seconds: float, every: int) -> list[tuple[float, np.ndarray]]:
    """``(altitude m, frame)`` for every drone at every ``every``-th step of ``seconds`` s."""
    scenario = load_scenario("case3")
    world = World(scenario, environment=env, seed=0)
    renderer = SceneRenderer.from_scenario(scenario, world.environment)
    pilot = PilotController(world.rng("pilot"))
    altitude = {d.id: d.altitude for d in scenario.drones}
    frames = []
    for k in range(int(round(seconds * scenario.rate_hz))):
        if k % every == 0:
            views = world.camera_views()
            frames += [(altitude[v.drone_id], renderer.render_view(v)) for v in views]
        world.step(pilot.control(world))
    renderer.close()
    return frames


def measure(env: str, frames: list, yolo: YoloDetector) -> dict[tuple[float, int], Tally]:
    """Run every frame raw and through JPEG at every quality; tallies by (altitude, quality)."""
    tallies: dict[tuple[float, int], Tally] = {}
    with progress_bar(f"{env}: detect raw + {len(QUALITIES)} qualities", len(frames)) as advance:
        for altitude, frame in frames:
            raw = yolo.detect_image(frame)
            for q in QUALITIES:
                start = time.perf_counter()
                data = encode_jpeg(frame, q)
                decoded = decode_jpeg(data)
                tally = tallies.setdefault((altitude, q), Tally())
                tally.codec_s.append(time.perf_counter() - start)
                tally.sizes.append(len(data))
                kept_iou, new = compare(raw, yolo.detect_image(decoded))
                tally.raw_detections += len(raw)
                tally.kept_iou += kept_iou
                tally.new += new
            advance()
    return tallies


def row(label: str, q: int, tallies: list[Tally], rate_hz: float) -> str:
    """One printed line: sizes, uplink, codec time and detection agreement of ``tallies``."""
    sizes = np.concatenate([t.sizes for t in tallies]) / 1000  # KB
    codec_ms = np.median(np.concatenate([t.codec_s for t in tallies])) * 1e3
    raw = sum(t.raw_detections for t in tallies)
    kept_iou = np.concatenate([t.kept_iou for t in tallies])
    kept = len(kept_iou) / raw if raw else float("nan")
    new = sum(t.new for t in tallies) / len(sizes)
    kb_s = sizes.mean() * rate_hz
    return (
        f"{label:>8s} {q:3d} {sizes.mean():8.1f} {np.percentile(sizes, 95):7.1f} {kb_s:6.0f} "
        f"{PAPER_RAW_MB_S * 1000 / kb_s:6.1f} {codec_ms:8.1f} {raw:5d} {kept:6.4f} "
        f"{kept_iou.mean():5.3f} {new:5.3f}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=120.0, help="simulated seconds per env")
    parser.add_argument("--every", type=int, default=5, help="render every N-th step (0.2 s)")
    args = parser.parse_args()
    if args.seconds <= 0 or args.every < 1:
        parser.error("--seconds must be > 0 and --every >= 1")

    scenario = load_scenario("case3")
    rate_hz = scenario.rate_hz
    yolo = YoloDetector(target_ids=scenario.target_ids)
    raw_kb = scenario.camera.detector_px**2 * 3 / 1000
    print(f"raw 640x640 RGB frame: {raw_kb:.0f} KB, {raw_kb * rate_hz:.0f} KB/s at {rate_hz:g} Hz;"
          f" paper's raw-image baseline: {PAPER_RAW_MB_S * 1000:.0f} KB/s per drone")  # fmt: skip
    header = (
        f"{'altitude':>8s} {'q':>3s} {'mean KB':>8s} {'p95 KB':>7s} {'KB/s':>6s} {'/paper':>6s} "
        f"{'codec ms':>8s} {'raw':>5s} {'kept':>6s} {'IoU':>5s} {'new':>5s}"
    )
    for env in ("crop_field", "orchard"):
        frames = render_frames(env, args.seconds, args.every)
        tallies = measure(env, frames, yolo)
        altitudes = sorted({a for a, _ in tallies}, reverse=True)
        print(f"\n{env}: {len(frames)} frames\n{header}")
        for q in QUALITIES:
            for a in altitudes:
                print(row(f"{a:g} m", q, [tallies[(a, q)]], rate_hz))
            print(row("all", q, [tallies[(a, q)] for a in altitudes], rate_hz))


if __name__ == "__main__":
    main()
