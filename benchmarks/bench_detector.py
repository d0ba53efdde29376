"""Vision-path latency: the frozen ONNX YOLO detector per 640 x 640 frame, and rendering.

Run: ``.venv/bin/python benchmarks/bench_detector.py [--frames 100] [--threads 1]``.

Frames are Case 3 camera views (drones 1-4 at 60, 40, 30, 20 m) in ``crop_field`` and
``orchard``, rendered once up front. The detector figure is the whole
:meth:`YoloDetector.detect_image` call on a 640 x 640 frame (resize to the network input,
ONNX Runtime with ``--threads`` intra-op threads, decoding and NMS): the goal is <= 50 ms on
1 thread (the paper: 130 ms on a Raspberry Pi 5). Render time is per frame of
:class:`SceneRenderer` (MuJoCo offscreen, CPU). Prints median and 95th percentile in ms.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from dronefl.config import load_scenario
from dronefl.perception.render import SceneRenderer
from dronefl.perception.yolo import YoloDetector, shipped_detector_path
from dronefl.sim.world import World


def percentiles(samples: list[float]) -> str:
    """``median / p95`` of ``samples`` (s) in ms."""
    ms = np.array(samples) * 1e3
    return f"median {np.median(ms):6.1f} ms   p95 {np.percentile(ms, 95):6.1f} ms"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100, help="timed frames per environment")
    parser.add_argument("--threads", type=int, default=1, help="ONNX Runtime intra-op threads")
    args = parser.parse_args()
    if args.frames < 1 or args.threads < 1:
        parser.error("--frames and --threads must be >= 1")

    scenario = load_scenario("case3")
    detector = YoloDetector(threads=args.threads, target_ids=scenario.target_ids)
    print(f"detector {shipped_detector_path().name}: input {detector.imgsz} px, "
          f"{args.threads} ONNX Runtime thread(s); {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores visible")  # fmt: skip
    for env in ("crop_field", "orchard"):
        world = World(scenario, environment=env, seed=0)
        renderer = SceneRenderer.from_scenario(scenario, world.environment)
        views = world.camera_views()
        render_s, frames = [], []
        for k in range(args.frames):
            start = time.perf_counter()
            frames.append(renderer.render_view(views[k % len(views)]))
            render_s.append(time.perf_counter() - start)
        renderer.close()
        for frame in frames[:5]:  # warm-up: first ONNX Runtime calls allocate
            detector.detect_image(frame)
        detect_s = []
        for frame in frames:
            start = time.perf_counter()
            detector.detect_image(frame)
            detect_s.append(time.perf_counter() - start)
        print(f"{env:10s} render 640x640: {percentiles(render_s)}")
        print(f"{env:10s} detect 640x640: {percentiles(detect_s)}")


if __name__ == "__main__":
    main()
