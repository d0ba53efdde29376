"""Change one part and compare: how much does the closed loop lose when the detector misses?

The drones' detector is swapped for one that drops each detection with probability ``miss``
(on top of the projection detector's own misses); everything else (pretrained models, fusion,
planner, seed) stays the paper's. Run it:

    python examples/change_one_part.py --out runs/example
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from dronefl.config import load_scenario
from dronefl.experiments.track import LoopParts, TrackConfig, run_episode
from dronefl.perception import make_detector
from dronefl.perception.base import Detector
from dronefl.report.tables import comparison
from dronefl.results.episode import EpisodeMetrics
from dronefl.sim.world import World
from dronefl.types import CameraView, Detection


class MissingDetector(Detector):
    """Another detector whose every detection is dropped with probability ``miss``."""

    name = "missing"

    def __init__(self, inner: Detector, miss: float, world: World) -> None:
        self.inner, self.miss = inner, miss
        self.rng = world.rng("missing-detector")  # its own seeded stream: the rest is unchanged

    def detect(self, view: CameraView) -> tuple[Detection, ...]:
        return tuple(d for d in self.inner.detect(view) if self.rng.random() >= self.miss)

    def state(self) -> tuple[object, dict]:
        """Both random streams, so that a resumed episode (``dronefl track --resume``)
        continues them."""
        return self.inner.state(), self.rng.bit_generator.state

    def restore(self, state: tuple[object, dict]) -> None:
        inner, own = state
        self.inner.restore(inner)
        self.rng.bit_generator.state = own


def compare(out: Path, miss: float = 0.5, duration: float = 120.0, **settings) -> str:
    """The same Case 1 episode with the paper's detector and with ``miss`` of its detections
    dropped; returns the side-by-side table. ``settings`` go to :class:`TrackConfig`."""
    config = TrackConfig(load_scenario("case1"), out / "paper", method="fixed",
                         duration=duration, **settings)  # fmt: skip

    def missing(name: str, world: World) -> Detector:
        return MissingDetector(make_detector(name, world), miss, world)

    results: list[EpisodeMetrics] = [
        run_episode(config),
        run_episode(replace(config, out=out / "missing"), LoopParts(detector=missing)),
    ]
    return comparison(results, labels=["paper", f"{miss:.0%} missed"])


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/example"))
    parser.add_argument("--miss", type=float, default=0.5)
    args = parser.parse_args()
    print(compare(args.out, args.miss))
