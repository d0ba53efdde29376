"""The world: field, vehicles and drones of one scenario, stepped at ``rate_hz`` (SPEC §2).

Every random draw comes from a generator derived from ``(seed, stream name)``, so the same seed
gives identical runs and adding a consumer of randomness (say a detector) leaves the vehicles'
motion unchanged.
"""

from __future__ import annotations

import zlib

import numpy as np

from dronefl.config import Environment, Scenario
from dronefl.sim.camera import PinholeCamera
from dronefl.sim.drones import DroneTeam
from dronefl.sim.environment import FarmEnvironment
from dronefl.sim.targets import TargetFleet
from dronefl.types import CameraView, DroneState, Odometry, TargetState


def stream_rng(seed: int, name: str) -> np.random.Generator:
    """A generator for the random stream ``name`` of run ``seed``."""
    return np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32(name.encode())]))


def drone_start_positions(scenario: Scenario, target_positions: np.ndarray) -> np.ndarray:
    """Every drone's start ``(M, 2)`` m: its ``start`` when the scenario gives one, else above
    the centre of the box around its targets' positions ``target_positions`` ``(N, 2)`` m
    (row j is target ``scenario.target_ids[j]``)."""
    column = {t: j for j, t in enumerate(scenario.target_ids)}
    starts = []
    for d in scenario.drones:
        if d.start is not None:
            starts.append(d.start)
            continue
        pts = target_positions[[column[i] for i in d.targets]]
        starts.append(0.5 * (pts.min(axis=0) + pts.max(axis=0)))
    return np.array(starts, dtype=float)


class World:
    """Simulated farm with ground vehicles and drones.

    ``environment`` overrides the scenario's default environment. Time ``t`` (s) starts at 0
    and advances by ``dt = 1 / rate_hz`` per :meth:`step`.
    """

    def __init__(
        self, scenario: Scenario, environment: Environment | None = None, seed: int = 0
    ) -> None:
        self.scenario = scenario
        self.seed = seed
        self.environment = FarmEnvironment(environment or scenario.environment, scenario.field)
        self.camera = PinholeCamera.from_spec(scenario.camera)
        self.dt = scenario.dt
        self.t = 0.0
        self.steps = 0
        self.targets = TargetFleet(scenario, stream_rng(seed, "targets"))
        starts = drone_start_positions(scenario, self.targets.position)
        self.drones = DroneTeam(scenario, starts, stream_rng(seed, "odometry"))

    def rng(self, name: str) -> np.random.Generator:
        """A generator for a named consumer of randomness in this run (e.g. ``'detector'``)."""
        return stream_rng(self.seed, name)

    def step(self, accelerations: np.ndarray) -> None:
        """Advance the world by one step with the drones' commanded accelerations ``(M, 2)``."""
        self.drones.step(accelerations, self.dt)
        self.targets.step(self.t, self.dt)
        self.steps += 1
        self.t = self.steps * self.dt

    def state(self) -> dict:
        """The clock, the vehicles' and the drones' state (:meth:`TargetFleet.state`,
        :meth:`DroneTeam.state`), for an episode checkpoint."""
        return {
            "t": self.t,
            "steps": self.steps,
            "targets": self.targets.state(),
            "drones": self.drones.state(),
        }

    def restore(self, state: dict) -> None:
        """Continue from ``state`` (:meth:`state` of a world of the same scenario, environment
        and seed)."""
        self.t, self.steps = float(state["t"]), int(state["steps"])
        self.targets.restore(state["targets"])
        self.drones.restore(state["drones"])

    def target_states(self) -> tuple[TargetState, ...]:
        """True states of all vehicles."""
        return self.targets.states()

    def drone_states(self) -> tuple[DroneState, ...]:
        """True states of all drones."""
        return self.drones.states()

    def odometry(self) -> list[Odometry]:
        """Every drone's noisy odometry at the current time."""
        return self.drones.odometry(self.t)

    def camera_views(self) -> list[CameraView]:
        """One camera view per drone (true scene, no image) at the current time."""
        targets = self.target_states()
        return [
            CameraView(int(i), self.t, pos, 0.0, targets)
            for i, pos in zip(self.drones.ids, self.drones.camera_positions(), strict=True)
        ]
