"""Camera frames of a recorded run, as the centralized baseline's cloud receives them.

A recorded run (``dronefl simulate``) holds every drone's position and altitude and every
target's position and heading at each step, which is all the renderer draws (the cameras look
straight down, yaw 0). :func:`render_run` draws every drone's frame of every step at the
detector size, sends it through the uplink's JPEG round trip (:func:`~dronefl.perception.uplink.
encode_jpeg` at ``quality``, bytes counted) and keeps the decoded frame downscaled to
``frame_px`` pixels (:func:`~dronefl.perception.uplink.downscale`), the image model's input.
The result is cached in the run folder (``frames_<px>px_q<quality>.npz``), so a run is
rendered once.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dronefl.config import parse_scenario
from dronefl.io import atomic_savez
from dronefl.logs import load_run
from dronefl.perception.render import SceneRenderer
from dronefl.perception.uplink import DEFAULT_JPEG_QUALITY, decode_jpeg, downscale, encode_jpeg
from dronefl.progress import progress_bar
from dronefl.sim.camera import PinholeCamera
from dronefl.sim.environment import FarmEnvironment
from dronefl.types import TargetState


@dataclass(frozen=True)
class RunFrames:
    """Every drone's frames of a run: ``frames`` ``(M, K, P, P, 3)`` uint8 (drones in
    ``drone_ids`` order) and the JPEG bytes each frame cost on the uplink, ``jpeg_bytes``
    ``(M, K)``."""

    drone_ids: tuple[int, ...]
    frames: np.ndarray
    jpeg_bytes: np.ndarray


def render_run(
    run_dir: Path,
    frame_px: int = 48,
    quality: int = DEFAULT_JPEG_QUALITY,
    progress: bool = True,
) -> RunFrames:
    """The frames of the recorded run in ``run_dir`` (module doc), rendered or from its cache."""
    run_dir = Path(run_dir)
    cache = run_dir / f"frames_{frame_px}px_q{quality}.npz"
    if cache.is_file():
        with np.load(cache) as data:
            drone_ids = tuple(int(i) for i in data["drone_ids"])
            return RunFrames(drone_ids, data["frames"], data["jpeg_bytes"])
    logs, truth = load_run(run_dir)
    meta = next(iter(logs.values())).meta
    scenario = parse_scenario(meta["scenario"], f"{run_dir} (metadata)")
    environment = FarmEnvironment(meta["environment"], scenario.field)
    renderer = SceneRenderer(
        PinholeCamera.from_spec(scenario.camera), scenario.vehicle, environment,
        scenario.target_ids,
    )  # fmt: skip
    drone_ids = tuple(int(i) for i in truth.drone_ids)
    m, k = len(drone_ids), len(truth.t)
    frames = np.zeros((m, k, frame_px, frame_px, 3), dtype=np.uint8)
    jpeg_bytes = np.zeros((m, k), dtype=np.int64)
    zero = np.zeros(2)
    try:
        with progress_bar(f"render {run_dir.name}", k, enabled=progress) as advance:
            for step in range(k):
                targets = [
                    TargetState(int(tid), truth.target_position[step, j], zero,
                                float(truth.target_heading[step, j]))
                    for j, tid in enumerate(truth.target_ids)
                ]  # fmt: skip
                for i in range(m):
                    camera = np.array([*truth.drone_position[step, i], truth.drone_altitude[i]])
                    data = encode_jpeg(renderer.render(camera, 0.0, targets), quality)
                    jpeg_bytes[i, step] = len(data)
                    frames[i, step] = downscale(decode_jpeg(data), frame_px)
                advance()
    finally:
        renderer.close()
    atomic_savez(cache, drone_ids=np.array(drone_ids), frames=frames, jpeg_bytes=jpeg_bytes)
    return RunFrames(drone_ids, frames, jpeg_bytes)
