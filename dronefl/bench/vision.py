"""Vision path on one thread: rendered Case 3 frames and the YOLO detector per 640 x 640 frame.

Frames are what Case 3's four drones (60, 40, 30, 20 m) see while the scripted pilot flies them,
taken at evenly spaced instants of a flight, rendered by :class:`SceneRenderer` (MuJoCo
offscreen on the CPU). The detector figure is the whole :meth:`YoloDetector.detect_image` call
(resize to the network input, ONNX Runtime, decoding, NMS). There is no reference run on this
machine; the paper's Raspberry Pi 5 figure (130 ms) is carried as ``paper_ms``.
"""

from __future__ import annotations

# MuJoCo reads MUJOCO_GL at its first import: the renderer module sets it, so it goes first.
from dronefl.perception.render import SceneRenderer  # isort: skip

from dataclasses import dataclass, replace
from itertools import cycle
from time import perf_counter

import numpy as np

from dronefl.bench.energy import EnergyMeter
from dronefl.bench.results import Benchmarks
from dronefl.bench.timing import latency, time_calls
from dronefl.config import Environment, Scenario
from dronefl.perception.yolo import YoloDetector
from dronefl.sim.pilot import PilotController
from dronefl.sim.world import World

#: The paper's YOLO latency per sample on a Raspberry Pi 5 (Table II), ms.
PAPER_DETECTOR_MS = 130.0


@dataclass(frozen=True)
class Frame:
    """One rendered camera frame: ``drone_id``, time ``t`` s, ``image`` ``(640, 640, 3)`` uint8,
    and the wall seconds its rendering took."""

    drone_id: int
    t: float
    image: np.ndarray
    render_seconds: float


def render_frames(
    scenario: Scenario, environment: Environment, count: int, duration: float
) -> list[Frame]:
    """About ``count`` frames (rounded up to whole sets of the drones' views) of ``scenario`` in
    ``environment``, taken at evenly spaced instants of ``duration`` s of scripted flight."""
    if count < 1 or duration <= 0:
        raise ValueError(f"need count >= 1 and duration > 0, got {count}, {duration}")
    world = World(scenario, environment, seed=0)
    pilot = PilotController(world.rng("pilot"))
    sets = -(-count // len(scenario.drones))
    every = max(1, int(duration * scenario.rate_hz) // sets)  # steps between sets
    renderer = SceneRenderer.from_scenario(scenario, world.environment)
    frames = []
    try:
        renderer.render_view(world.camera_views()[0])  # warm-up: the first frame sets up OpenGL
        for _ in range(sets):
            for view in world.camera_views():
                started = perf_counter()
                image = renderer.render_view(view)
                frames.append(Frame(view.drone_id, view.t, image, perf_counter() - started))
            for _ in range(every):
                world.step(pilot.control(world))
    finally:
        renderer.close()
    return frames


def bench_detector(
    frames: dict[str, list[Frame]],
    target_ids: tuple[int, ...],
    measure_energy: EnergyMeter | None = None,
) -> Benchmarks:
    """Per 640 x 640 frame, ms, of ``frames`` (per environment):

    * ``detector``: the shipped YOLO11n on ONNX Runtime, 1 intra-op thread, all frames of every
      environment (each once, after 5 warm-up calls), with ``per_environment`` figures;
    * ``render``: MuJoCo rendering of each frame (CPU), with ``per_environment`` figures.

    With ``measure_energy`` the detector's energy per frame is measured too.
    """
    detector = YoloDetector(threads=1, target_ids=target_ids)
    per_env, all_seconds = {}, []
    for env, env_frames in frames.items():
        # Cycled: after the 5 warm-up calls the timed calls see every frame once.
        images = cycle([f.image for f in env_frames])
        seconds = time_calls(lambda it=images: detector.detect_image(next(it)), len(env_frames))
        per_env[env] = latency(f"YOLO11n, 640x640 {env} frame", seconds, "ms", 1)
        all_seconds.append(seconds)
    render_all = [f.render_seconds for fs in frames.values() for f in fs]
    what = f"YOLO11n ONNX, one 640x640 frame (network input {detector.imgsz} px)"
    detector_figure = replace(
        latency(what, np.concatenate(all_seconds), "ms", 1),
        per_environment=per_env,
        paper_ms=PAPER_DETECTOR_MS,
    )
    render = replace(
        latency("MuJoCo render on the CPU, one 640x640 frame", render_all, "ms", 1),
        per_environment={
            env: latency(f"render, {env}", [f.render_seconds for f in fs], "ms", 1)
            for env, fs in frames.items()
        },
    )
    if measure_energy is not None:
        image = next(iter(frames.values()))[0].image
        calls = sum(len(fs) for fs in frames.values())
        reading = measure_energy(lambda: detector.detect_image(image), calls)
        detector_figure = replace(detector_figure, energy_reading=reading)
    return Benchmarks(detector=detector_figure, render=render)
