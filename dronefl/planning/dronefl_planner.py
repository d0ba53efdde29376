"""The DroneFL planner: one-step cost minimisation over all drones' accelerations (SPEC §7)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dronefl.config import Scenario
from dronefl.planning.base import Plan, PlanCost, Planner
from dronefl.sim.camera import PinholeCamera
from dronefl.tracking.fusion import TrackForecast
from dronefl.types import DroneState

#: Most drones that may see one target next step: the uncertainty lookup table has 2^k rows.
MAX_OBSERVERS = 16
_EPS = 1e-9  # m, m/s: slack on the bound checks so that points on a bound count as inside


@dataclass(frozen=True)
class PlannerConfig:
    """Weights and solver settings of :class:`DroneFLPlanner`.

    ``alpha`` weight of ``sum_j Tr P_j`` (paper: 50); ``omega`` weight of ``sum_i ||u_i||`` (paper:
    0.005, per m/s^2); ``min_distance`` ``h`` m, below which getting closer to a target earns
    nothing. Solver: a polar grid of ``directions`` x ``magnitudes`` accelerations per drone, then
    ``refinements`` levels of a 3 x 3 pattern search whose spacing starts at ``max_accel / 4`` and
    halves each level; each stage runs coordinate descent over the drones for at most
    ``max_sweeps`` sweeps.
    """

    alpha: float = 50.0
    omega: float = 0.005
    min_distance: float = 1.0
    directions: int = 16
    magnitudes: int = 3
    refinements: int = 5
    max_sweeps: int = 6

    def __post_init__(self) -> None:
        for name in ("alpha", "omega", "min_distance"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name}: must be a finite number >= 0, got {value!r}")
        for name, least in (
            ("directions", 3),
            ("magnitudes", 1),
            ("refinements", 0),
            ("max_sweeps", 1),
        ):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= least):
                raise ValueError(f"{name}: must be an integer >= {least}, got {value!r}")


@dataclass(frozen=True)
class PlannedDrone:
    """What the planner knows of one drone: bounds ``max_speed`` m/s and ``max_accel`` m/s^2, the
    camera ``footprint_half_extent`` ``(hx, hy)`` m on the ground at its altitude (nadir camera,
    yaw 0: an axis-aligned rectangle centred below the drone) and its assigned ``targets`` N_i."""

    drone_id: int
    max_speed: float
    max_accel: float
    footprint_half_extent: tuple[float, float]
    targets: tuple[int, ...]


class DroneFLPlanner(Planner):
    r"""Chooses every drone's acceleration ``u_i`` (m/s^2) for the next step of ``dt`` s by

    .. math::
        \min_{u}\ J(u) = \sum_i \sum_{j \in N_i} \max(\|p_{i,t+1} - z_{j,t+1}\|, h)
            + \alpha \sum_j \mathrm{Tr}\, P_{j,t+1}(A_j) + \omega \sum_i \|u_i\|

    with ``p_{i,t+1} = p_i + v_i dt + u_i dt^2 / 2`` and ``v_{i,t+1} = v_i + u_i dt``, subject to
    ``||u_i|| <= max_accel``, ``||v_{i,t+1}|| <= max_speed`` and the drone staying in the field
    ``[0, W] x [0, H]``. ``z_j`` is the fused position of target ``j``; ``A_j`` the drones whose
    camera footprint at ``p_{i,t+1}`` contains ``z_j``; ``P_{j,t+1}(A_j)`` the covariance after the
    next predict step and the updates of ``A_j`` with their adapted ``R``
    (:meth:`TrackForecast.trace_table`), so moving a drone changes the uncertainty term.

    The field bound is enforced as a viability constraint: the next position *and* the point where
    the drone would come to rest under full braking, ``p_{t+1} + v_{t+1}\|v_{t+1}\| / (2 a_max)``,
    must lie in the field. A drone that satisfies it can always brake in time (full braking keeps
    that rest point fixed), so the constraint set is never empty; a drone that starts outside it
    (e.g. placed at full speed next to the edge) brakes.

    Solver: the distance and effort terms are separable per drone, the uncertainty term couples
    drones only through shared targets and is piecewise constant in the positions. Each stage
    evaluates a candidate set per drone (stage 0: zero, full braking, the move toward the
    geometric median of the drone's targets, and a polar grid; later stages: a 3 x 3 pattern
    around the incumbent with halving spacing) and runs coordinate descent across the drones on
    the exact ``J``, looking ``Tr P_j`` up in a per-target table over all subsets of the drones
    that could see ``j`` next step. Each stage keeps the incumbent, so ``J`` never increases.
    """

    def __init__(
        self,
        drones: Sequence[PlannedDrone],
        field_size: tuple[float, float],
        dt: float,
        config: PlannerConfig | None = None,
    ) -> None:
        if not drones:
            raise ValueError("the planner needs at least one drone")
        ids = [d.drone_id for d in drones]
        if len(set(ids)) != len(ids):
            raise ValueError(f"drone ids must be unique, got {ids}")
        for d in drones:
            if not (d.max_speed > 0 and d.max_accel > 0):
                raise ValueError(f"drone {d.drone_id}: max_speed and max_accel must be > 0")
            if not min(d.footprint_half_extent) > 0:
                raise ValueError(f"drone {d.drone_id}: footprint half extents must be > 0 m")
        if not (dt > 0 and min(field_size) > 0):
            raise ValueError(f"need dt > 0 s and a positive field size, got {dt}, {field_size}")
        self.config = config or PlannerConfig()
        self.drones = tuple(drones)
        self.drone_ids = tuple(ids)
        self.dt = float(dt)
        self.upper = np.array(field_size, dtype=float)  # field corner (W, H), m
        self.max_accel = np.array([d.max_accel for d in drones], dtype=float)
        self.max_speed = np.array([d.max_speed for d in drones], dtype=float)
        self.half_extent = np.array([d.footprint_half_extent for d in drones], dtype=float)
        cfg = self.config
        angles = 2 * np.pi * np.arange(cfg.directions) / cfg.directions
        rings = np.arange(1, cfg.magnitudes + 1) / cfg.magnitudes
        # Unit-disc grid (directions * magnitudes, 2), scaled per drone by max_accel.
        self._polar = (
            rings[:, None, None] * np.stack([np.cos(angles), np.sin(angles)], -1)
        ).reshape(-1, 2)
        self._stencil = np.stack(np.meshgrid([-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0]), -1).reshape(-1, 2)
        self._centre = 4  # index of (0, 0) in the stencil

    @classmethod
    def from_scenario(
        cls, scenario: Scenario, config: PlannerConfig | None = None
    ) -> DroneFLPlanner:
        """A planner for ``scenario``'s drones, camera, field and step."""
        camera = PinholeCamera.from_spec(scenario.camera)
        drones = [
            PlannedDrone(
                d.id,
                d.max_speed,
                d.max_accel,
                camera.footprint_half_extent(d.altitude),
                tuple(d.targets),
            )
            for d in scenario.drones
        ]
        return cls(drones, (scenario.field.width, scenario.field.height), scenario.dt, config)

    def plan(self, drones: Sequence[DroneState], forecast: TrackForecast) -> Plan:
        step = _Step(self, drones, forecast)
        m_idx = np.arange(len(self.drones))
        candidates = step.initial_candidates()
        choice = step.descend(candidates, fallback=1, start=None)  # fallback: full braking
        u = candidates[m_idx, choice]
        for level in range(self.config.refinements):
            spacing = self.max_accel * 0.25 / 2**level  # (M,) m/s^2
            for _ in range(3):  # re-centre at most twice per level before refining further
                candidates = _clip_norm(
                    u[:, None, :] + spacing[:, None, None] * self._stencil, self.max_accel
                )
                choice = step.descend(candidates, fallback=self._centre, start=self._centre)
                if (choice == self._centre).all():
                    break
                u = candidates[m_idx, choice]
        return step.result(u)

    def cost(
        self, drones: Sequence[DroneState], forecast: TrackForecast, accelerations: np.ndarray
    ) -> PlanCost:
        """``J`` of the given ``accelerations`` ``(M, 2)`` m/s^2 (planner drone order), bounds
        not checked."""
        return _Step(self, drones, forecast).result(np.asarray(accelerations, dtype=float)).cost


def _clip_norm(u: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """Scale the rows of ``u`` ``(M, K, 2)`` that lie outside the disc of radius ``limit``
    ``(M,)`` onto its rim."""
    norm = np.linalg.norm(u, axis=-1)
    return u * np.minimum(1.0, limit[:, None] / np.maximum(norm, 1e-300))[..., None]


class _Step:
    """The arrays of one planning call (drones in planner order, targets in forecast order)."""

    def __init__(
        self, planner: DroneFLPlanner, drones: Sequence[DroneState], forecast: TrackForecast
    ) -> None:
        self.planner = planner
        cfg = planner.config
        by_id = {d.drone_id: d for d in drones}
        if set(by_id) != set(planner.drone_ids) or len(drones) != len(planner.drone_ids):
            raise ValueError(
                f"plan needs exactly the drones {planner.drone_ids}, "
                f"got {[d.drone_id for d in drones]}"
            )
        missing = [i for i in planner.drone_ids if i not in forecast.drone_ids]
        if missing:
            raise ValueError(f"the forecast has no noise model for drones {missing}")
        states = [by_id[i] for i in planner.drone_ids]
        self.p = np.array([s.position for s in states], dtype=float)  # (M, 2) m
        self.v = np.array([s.velocity for s in states], dtype=float)  # (M, 2) m/s
        if not (np.isfinite(self.p).all() and np.isfinite(self.v).all()):
            raise ValueError("drone positions and velocities must be finite")
        dt = planner.dt
        self.c = 0.5 * dt**2  # s^2: next position moves c * u
        self.p0 = self.p + self.v * dt  # (M, 2) next positions with u = 0
        self.forecast = forecast
        self.z = np.asarray(forecast.positions, dtype=float)  # (T, 2)
        n_drones, n_targets = len(states), len(self.z)
        column = {j: k for k, j in enumerate(forecast.target_ids)}
        self.assigned = np.zeros((n_drones, n_targets))  # (M, T) 1 where j in N_i and tracked
        for i, d in enumerate(planner.drones):
            for j in d.targets:
                if j in column:
                    self.assigned[i, column[j]] = 1.0
        # Drones that could hold z_j in their footprint next step, whatever their u.
        reach = planner.half_extent + self.c * planner.max_accel[:, None] + _EPS  # (M, 2)
        gap = np.abs(self.z[None, :, :] - self.p0[:, None, :])  # (M, T, 2)
        self.may_see = (gap <= reach[:, None, :]).all(-1)  # (M, T)
        counts = self.may_see.sum(0)
        if n_targets and counts.max() > MAX_OBSERVERS:
            raise ValueError(f"more than {MAX_OBSERVERS} drones may see one target")
        bit_index = np.cumsum(self.may_see, axis=0) - 1  # (M, T) bit of drone i in table j
        self.bit = np.where(self.may_see, np.left_shift(1, np.maximum(bit_index, 0)), 0)
        width = 2 ** int(counts.max()) if n_targets else 1
        self.tables = np.zeros((n_targets, width))  # (T, 2^k) Tr P_j per observer subset
        forecast_index = [forecast.drone_ids.index(i) for i in planner.drone_ids]
        for j in range(n_targets):
            observers = [forecast_index[i] for i in np.flatnonzero(self.may_see[:, j])]
            table = forecast.trace_table(j, observers)
            self.tables[j, : len(table)] = table
        self.alpha, self.omega, self.h = cfg.alpha, cfg.omega, cfg.min_distance

    def initial_candidates(self) -> np.ndarray:
        """Stage-0 accelerations ``(M, K, 2)``: zero, full braking, toward the geometric median
        of the assigned targets (exact, and at full and half ``max_accel``), the polar grid."""
        planner, dt = self.planner, self.planner.dt
        a_max = planner.max_accel
        brake = _clip_norm(-self.v[:, None, :] / dt, a_max)[:, 0]
        goal = self._geometric_median()
        toward = (goal - self.p0) / self.c  # u that puts the next position on the median
        norm = np.linalg.norm(toward, axis=-1, keepdims=True)
        unit = np.where(norm > 0, toward / np.maximum(norm, 1e-300), 0.0)
        exact = _clip_norm(toward[:, None, :], a_max)[:, 0]
        fixed = np.stack(
            [np.zeros_like(brake), brake, exact, unit * a_max[:, None], unit * a_max[:, None] / 2],
            axis=1,
        )
        grid = a_max[:, None, None] * planner._polar[None]
        return np.concatenate([fixed, grid], axis=1)

    def _geometric_median(self) -> np.ndarray:
        """Weiszfeld iterations for ``argmin_g sum_{j in N_i} ||g - z_j||`` per drone, ``(M, 2)``
        m; drones with no tracked target keep their drift point ``p0``."""
        w = self.assigned
        total = w.sum(1, keepdims=True)
        has = total[:, 0] > 0
        g = np.where(has[:, None], (w @ self.z) / np.maximum(total, 1.0), self.p0)
        for _ in range(20):
            d = np.linalg.norm(g[:, None, :] - self.z[None], axis=-1)  # (M, T)
            # Floor the distance so a median on a target stays finite (it is then optimal).
            wd = w / np.maximum(d, 1e-6)
            g = np.where(
                has[:, None], (wd @ self.z) / np.maximum(wd.sum(1, keepdims=True), 1e-300), g
            )
        return g

    def evaluate(self, u: np.ndarray, fallback: int) -> tuple[np.ndarray, np.ndarray]:
        """Separable cost ``(M, K)`` (``inf`` where a bound is broken) and the footprint bits
        ``(M, K, T)`` of candidates ``u`` ``(M, K, 2)``. A drone with no admissible candidate
        keeps candidate ``fallback`` (see the class docstring)."""
        planner = self.planner
        p_next = self.p0[:, None, :] + self.c * u  # (M, K, 2)
        v_next = self.v[:, None, :] + planner.dt * u
        speed = np.linalg.norm(v_next, axis=-1)  # (M, K)
        rest = p_next + v_next * (speed / (2 * planner.max_accel[:, None]))[..., None]
        inside = (
            (p_next >= -_EPS)
            & (p_next <= planner.upper + _EPS)
            & (rest >= -_EPS)
            & (rest <= planner.upper + _EPS)
        ).all(-1)
        ok = inside & (speed <= planner.max_speed[:, None] + _EPS)
        stuck = ~ok.any(1)
        ok[stuck, fallback] = True
        diff = self.z[None, None, :, :] - p_next[:, :, None, :]  # (M, K, T, 2)
        dist = np.sqrt((diff**2).sum(-1))
        sep = (np.maximum(dist, self.h) * self.assigned[:, None, :]).sum(-1)
        sep += self.omega * np.linalg.norm(u, axis=-1)
        seen = (np.abs(diff) <= planner.half_extent[:, None, None, :]).all(-1)
        bits = np.where(seen, self.bit[:, None, :], 0)  # (M, K, T)
        return np.where(ok, sep, np.inf), bits

    def descend(self, u: np.ndarray, fallback: int, start: int | None) -> np.ndarray:
        """Coordinate descent over drones on the exact ``J``; returns the chosen candidate index
        per drone ``(M,)``, starting from ``start`` (or each drone's separable best)."""
        sep, bits = self.evaluate(u, fallback)
        n_drones, n_targets = bits.shape[0], bits.shape[2]
        choice = np.argmin(sep, axis=1) if start is None else np.full(n_drones, start)
        rows = np.arange(n_drones)
        chosen = bits[rows, choice]  # (M, T)
        total = chosen.sum(0)  # (T,) bits are disjoint per drone, so the sum is the union
        columns = np.arange(n_targets)
        for _ in range(self.planner.config.max_sweeps):
            changed = False
            for i in range(n_drones):
                others = total - chosen[i]
                masks = others[None, :] + bits[i]  # (K, T)
                cost = sep[i] + self.alpha * self.tables[columns, masks].sum(1)
                best = int(np.argmin(cost))
                # Move only on a strict improvement so that ties cannot make the sweep cycle.
                if cost[best] < cost[choice[i]] - 1e-12:
                    choice[i] = best
                    chosen[i] = bits[i, best]
                    total = others + chosen[i]
                    changed = True
            if not changed:
                break
        return choice

    def result(self, u: np.ndarray) -> Plan:
        """The :class:`Plan` (with its exact cost) of accelerations ``u`` ``(M, 2)``."""
        planner = self.planner
        p_next = self.p0 + self.c * u
        diff = self.z[None, :, :] - p_next[:, None, :]  # (M, T, 2)
        dist = np.linalg.norm(diff, axis=-1)
        distance = float((np.maximum(dist, self.h) * self.assigned).sum())
        seen = (np.abs(diff) <= planner.half_extent[:, None, :]).all(-1) & self.may_see
        masks = np.where(seen, self.bit, 0).sum(0)  # (T,)
        uncertainty = self.alpha * float(self.tables[np.arange(len(self.z)), masks].sum())
        effort = self.omega * float(np.linalg.norm(u, axis=-1).sum())
        ids = planner.drone_ids
        observers = {
            j: tuple(ids[i] for i in np.flatnonzero(seen[:, k]))
            for k, j in enumerate(self.forecast.target_ids)
        }
        return Plan(
            accelerations={i: u[k].copy() for k, i in enumerate(ids)},
            positions={i: p_next[k].copy() for k, i in enumerate(ids)},
            observers=observers,
            cost=PlanCost(distance, uncertainty, effort),
        )
