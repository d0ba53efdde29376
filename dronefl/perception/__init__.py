"""Perception on the drone: detectors and (optionally) rendered camera frames."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from dronefl.perception.base import Detector
    from dronefl.sim.world import World

DETECTORS = ("projection", "yolo")


def make_detector(name: str, world: World) -> Detector:
    """Build the detector ``name`` (``projection`` or ``yolo``) for the drones of ``world``."""
    if name == "projection":
        from dronefl.perception.projection import ProjectionDetector

        return ProjectionDetector(
            world.camera, world.scenario.vehicle, world.environment, world.rng("detector")
        )
    if name == "yolo":
        from dronefl.perception.yolo import YoloDetector

        return YoloDetector.for_world(world)
    raise ValueError(f"--detector: unknown detector {name!r} (choose from {', '.join(DETECTORS)})")
