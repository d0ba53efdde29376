"""Ground vehicles that work the field along boustrophedon paths (SPEC §2).

Each vehicle works the lanes ``{lane + k * lane_shift}`` that lie in the field: it drives a lane
to the headland, makes a semicircular U-turn of radius ``lane_shift * lane_spacing / 2`` onto the
next lane of its set, and at the edge of the field reverses the sweep. The path is a closed loop
(one full sweep up and back), so a run of any length follows it by arc length modulo its length.

Motion models (per target):

* ``constant_speed``: ``s_{t+1} = s_t + v dt`` and ``p_t = path(s_t)``.
* ``random_walk``: the reference ``r_t = path(s_t)`` advances as above and the vehicle moves as
  ``p_{t+1} = p_t + dt (v tau(s_t) + k (r_t - p_t) + w_t)``, with ``tau`` the path tangent,
  ``k = path_gain`` (1/s) the driver steering back to its path and ``w_t ~ N(0, walk_std^2 I)``
  m/s re-drawn every ``walk_period`` s; positions stay inside the field.
"""

from __future__ import annotations

import math

import numpy as np

from dronefl.config import FieldSpec, Scenario, TargetSpec
from dronefl.types import TargetState

#: Spacing of the points of a path polyline, m.
PATH_RESOLUTION = 0.25
#: Vehicles keep this far from the field's edge, m.
EDGE_MARGIN = 1.0


class VehiclePath:
    """A closed boustrophedon path as a dense polyline parametrised by arc length ``s`` (m)."""

    def __init__(self, spec: TargetSpec, field: FieldSpec) -> None:
        lanes = _lane_cycle(spec, field)
        east = spec.heading == "east"
        x_west, x_east = field.headland, field.width - field.headland
        pieces: list[np.ndarray] = []
        y0 = field.lane_y(lanes[0])
        pieces.append(_straight((spec.start_x, y0), (x_east if east else x_west, y0)))
        n_turns = len(lanes) - 1
        for k, (lane_from, lane_to) in enumerate(zip(lanes[:-1], lanes[1:], strict=True)):
            y_from, y_to = field.lane_y(lane_from), field.lane_y(lane_to)
            x_end = x_east if east else x_west
            pieces.append(_u_turn(x_end, y_from, y_to, bulge=1.0 if east else -1.0))
            east = not east
            x_far = x_east if east else x_west
            x_near = x_west if east else x_east
            end_x = spec.start_x if k == n_turns - 1 else x_far
            pieces.append(_straight((x_near, y_to), (end_x, y_to)))
        points = np.concatenate(pieces)
        keep = np.ones(len(points), dtype=bool)
        keep[1:] = np.linalg.norm(np.diff(points, axis=0), axis=1) > 1e-9
        self.points = points[keep]  # (K, 2) m
        seg = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        self.s = np.concatenate([[0.0], np.cumsum(seg)])  # (K,) m
        self.length = float(self.s[-1])

    def at(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """Position ``(2,)`` m and unit tangent ``(2,)`` at arc length ``s`` (wrapped)."""
        s = s % self.length
        k = int(np.searchsorted(self.s, s, side="right")) - 1
        k = min(max(k, 0), len(self.s) - 2)
        a, b = self.points[k], self.points[k + 1]
        frac = (s - self.s[k]) / (self.s[k + 1] - self.s[k])
        tangent = (b - a) / np.linalg.norm(b - a)
        return a + frac * (b - a), tangent


def _lane_cycle(spec: TargetSpec, field: FieldSpec) -> list[int]:
    """Lanes visited in one closed cycle, starting and ending on ``spec.lane``."""
    first = spec.lane % spec.lane_shift
    lanes = list(range(first, field.n_lanes, spec.lane_shift))
    i0 = lanes.index(spec.lane)
    up = lanes[i0:] + lanes[-2::-1] + lanes[1 : i0 + 1]
    return up


def _straight(a: tuple[float, float], b: tuple[float, float]) -> np.ndarray:
    n = max(2, int(math.ceil(math.dist(a, b) / PATH_RESOLUTION)) + 1)
    return np.linspace(a, b, n)


def _u_turn(x_end: float, y_from: float, y_to: float, bulge: float) -> np.ndarray:
    """Semicircle from ``(x_end, y_from)`` to ``(x_end, y_to)`` bulging towards ``bulge * x``."""
    radius = abs(y_to - y_from) / 2
    centre_y = (y_from + y_to) / 2
    n = max(8, int(math.ceil(math.pi * radius / PATH_RESOLUTION)))
    # The angle runs from +-pi/2 to -+pi/2; |cos| puts the arc on the headland side.
    start = math.copysign(math.pi / 2, y_from - centre_y)
    angles = np.linspace(start, -start, n)
    return np.stack(
        [x_end + bulge * radius * np.abs(np.cos(angles)), centre_y + radius * np.sin(angles)],
        axis=-1,
    )


class TargetFleet:
    """All ground vehicles of a scenario, stepped together with one random generator."""

    def __init__(self, scenario: Scenario, rng: np.random.Generator) -> None:
        self.scenario = scenario
        self.specs = scenario.targets
        self.ids = np.array(scenario.target_ids)
        self.paths = [VehiclePath(t, scenario.field) for t in self.specs]
        self.rng = rng
        n = len(self.specs)
        self.arc = np.zeros(n)  # arc length along each path, m
        self.position = np.zeros((n, 2))
        self.velocity = np.zeros((n, 2))
        self.heading = np.zeros(n)
        self.walk = np.zeros((n, 2))  # current random-walk velocity, m/s
        self._next_walk_draw = np.zeros(n)
        for j, path in enumerate(self.paths):
            point, tangent = path.at(0.0)
            self.position[j] = point
            self.velocity[j] = self.specs[j].speed * tangent
            self.heading[j] = math.atan2(tangent[1], tangent[0])

    def step(self, t: float, dt: float) -> None:
        """Advance every vehicle from time ``t`` to ``t + dt`` (s)."""
        field = self.scenario.field
        for j, (spec, path) in enumerate(zip(self.specs, self.paths, strict=True)):
            self.arc[j] += spec.speed * dt
            reference, tangent = path.at(self.arc[j])
            self.heading[j] = math.atan2(tangent[1], tangent[0])
            if spec.motion == "constant_speed":
                self.velocity[j] = spec.speed * tangent
                self.position[j] = reference
                continue
            if t + 1e-9 >= self._next_walk_draw[j]:
                self.walk[j] = self.rng.normal(0.0, spec.walk_std, size=2)
                self._next_walk_draw[j] = t + spec.walk_period
            velocity = spec.speed * tangent + spec.path_gain * (reference - self.position[j])
            velocity = velocity + self.walk[j]
            new = self.position[j] + velocity * dt
            new = np.clip(new, EDGE_MARGIN, [field.width - EDGE_MARGIN, field.height - EDGE_MARGIN])
            self.velocity[j] = (new - self.position[j]) / dt
            self.position[j] = new

    def state(self) -> dict:
        """Everything that changes as the vehicles move (arrays and the random generator's
        state), for an episode checkpoint; :meth:`restore` takes it back."""
        return {
            "arc": self.arc.copy(), "position": self.position.copy(),
            "velocity": self.velocity.copy(), "heading": self.heading.copy(),
            "walk": self.walk.copy(), "next_walk_draw": self._next_walk_draw.copy(),
            "rng": self.rng.bit_generator.state,
        }  # fmt: skip

    def restore(self, state: dict) -> None:
        """Continue from ``state`` (:meth:`state` of a fleet of the same scenario)."""
        self.arc, self.position = state["arc"].copy(), state["position"].copy()
        self.velocity, self.heading = state["velocity"].copy(), state["heading"].copy()
        self.walk, self._next_walk_draw = state["walk"].copy(), state["next_walk_draw"].copy()
        self.rng.bit_generator.state = state["rng"]

    def states(self) -> tuple[TargetState, ...]:
        """Current true states of all vehicles, in scenario order."""
        return tuple(
            TargetState(
                int(i), self.position[j].copy(), self.velocity[j].copy(), float(self.heading[j])
            )
            for j, i in enumerate(self.ids)
        )
