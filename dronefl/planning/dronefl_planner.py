"""The DroneFL planner: one-step cost minimisation over all drones' accelerations (SPEC §7)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dronefl.config import Scenario
from dronefl.planning.base import Plan, PlanCost, Planner
from dronefl.settings import DISTANCE_POINTS
from dronefl.sim.camera import PinholeCamera
from dronefl.tracking.fusion import TrackForecast
from dronefl.types import DroneState
from dronefl.validation import check_one_of

#: Most drones that may see one target next step: the uncertainty lookup table has 2^k rows.
MAX_OBSERVERS = 16
_EPS = 1e-9  # m, m/s: slack on the bound checks so that points on a bound count as inside


@dataclass(frozen=True)
class PlannerConfig:
    r"""Weights and solver settings of :class:`DroneFLPlanner`.

    ``alpha`` weight of ``sum_j Tr P_j`` (paper: 50); ``omega`` weight of ``sum_i ||u_i||`` (paper:
    0.005, per m/s^2); ``min_distance`` ``h`` m, below which getting closer to a target earns
    nothing. Solver (see :class:`DroneFLPlanner`): a polar grid of ``directions`` x
    ``magnitudes`` accelerations per drone; ``refinements`` levels of a 3 x 3 pattern search
    whose spacing starts at ``max_accel / 4`` and halves each level (final resolution
    ``max_accel / 2^(refinements + 1)``); the drones' footprint patterns are combined
    exhaustively up to ``max_combinations`` joint choices, beyond that by coordinate descent of at
    most ``max_sweeps`` sweeps.

    ``distance_at``: where the distance term measures drone ``i``: ``next`` (the paper) at its
    next position ``p_{i,t+1}``; ``rest`` at the point where it would come to rest under full
    braking (the point the field bound already keeps in the field),

    .. math::
        r_i = p_{i,t+1} + v_{i,t+1} \|v_{i,t+1}\| / (2 a_{max}).

    A one-step cost on ``p_{t+1}`` alone never pays for braking: inside ``h`` it is flat,
    outside it pulls at full acceleration toward the target whatever the drone's speed. When
    the target's estimate errs along the drone's own velocity (measured in Case 1's fused
    tracks: by 0.1-0.18 s of it), that pull keeps a tangential component and the drone orbits
    its target where the pull is the centripetal acceleration (``|v|^2 / r = a_max``: 3.1 m at
    2.3 m/s for ``a_max = 2``). At the rest point speed costs distance, so the planner brakes it
    out. Following a target at speed ``s`` puts ``r_i`` ``s^2 / (2 a_max)`` ahead of the drone
    (6 cm at the targets' 0.5 m/s). The rest point relative to each target (``v - \dot z_j``
    with the fused velocity) was tried and dropped: the velocity estimates' noise made the
    drones of Case 3 chatter (docs/fusion.md, "The planner's rest point").
    """

    alpha: float = 50.0
    omega: float = 0.005
    min_distance: float = 1.0
    directions: int = 16
    magnitudes: int = 3
    refinements: int = 6
    max_combinations: int = 4096
    max_sweeps: int = 6
    distance_at: str = "next"

    def __post_init__(self) -> None:
        check_one_of(self.distance_at, DISTANCE_POINTS, "distance_at")
        for name in ("alpha", "omega", "min_distance"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{name}: must be a finite number >= 0, got {value!r}")
        for name, least in (
            ("directions", 3),
            ("magnitudes", 1),
            ("refinements", 0),
            ("max_combinations", 1),
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
    ``[0, W] x [0, H]``; with ``config.distance_at = "rest"`` the distance term measures from
    each drone's rest point instead of ``p_{i,t+1}`` (:class:`PlannerConfig`). ``z_j`` is the
    fused position of target ``j``; ``A_j`` the drones whose
    camera footprint at ``p_{i,t+1}`` contains ``z_j``; ``P_{j,t+1}(A_j)`` the covariance after the
    next predict step and the updates of ``A_j`` with their adapted ``R``
    (:meth:`TrackForecast.trace_table`), so moving a drone changes the uncertainty term.

    The field bound is enforced as a viability constraint: the next position *and* the point where
    the drone would come to rest under full braking, ``p_{t+1} + v_{t+1}\|v_{t+1}\| / (2 a_max)``,
    must lie in the field. A drone that satisfies it can always brake in time (full braking keeps
    that rest point fixed), so the constraint set is never empty; a drone that starts outside it
    (e.g. placed at full speed next to the edge) brakes.

    Solver. The distance and effort terms are separable per drone and convex in ``u_i`` (not
    at the rest point, which the stage-1 grid and the brute-force tests cover); the
    uncertainty term couples drones only through shared targets and depends on ``u`` only through
    each drone's footprint *pattern* (which targets it would hold), which is piecewise constant.
    So ``J = sum_i c_i(u_i) + alpha sum_j Tr P_j(patterns)``, and the solver works per pattern:

    1. per drone, a candidate set (zero, full braking, the move toward the geometric median of
       its targets, a polar grid, and for every target the nearest-to-the-median and the
       least-effort point of the acceleration box that keeps it in the footprint) is evaluated
       and the best admissible candidate of every distinct pattern kept;
    2. each (drone, pattern) incumbent is refined by a 3 x 3 pattern search with halving
       spacing, restricted to the same pattern and the bounds (the separable cost is convex);
    3. one pattern per drone is chosen by exhaustive enumeration of the joint choices (or
       coordinate descent when there are too many), ``Tr P_j`` looked up in a per-target table
       over all subsets of the drones that could see ``j`` next step
       (:meth:`TrackForecast.trace_table`).

    Patterns that no stage-1 candidate hits (slivers thinner than the grid) are missed; the tests
    compare with a brute-force dense grid.
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
        """The accelerations minimising ``J`` for ``drones`` (exactly this planner's drone ids,
        any order; ``position`` m and ``velocity`` m/s are read) given the fused ``forecast``
        (:meth:`Fuser.forecast` with this planner's ``dt``)."""
        step = _Step(self, drones, forecast)
        incumbents = step.pattern_incumbents()
        step.refine(incumbents)
        choice = step.combine(incumbents)
        return step.result(incumbents.u[choice])

    def cost(
        self, drones: Sequence[DroneState], forecast: TrackForecast, accelerations: np.ndarray
    ) -> PlanCost:
        """``J`` of the given ``accelerations`` ``(M, 2)`` m/s^2 (planner drone order), bounds
        not checked."""
        return _Step(self, drones, forecast).result(np.asarray(accelerations, dtype=float)).cost


def _rest_point(
    p_next: np.ndarray, v_next: np.ndarray, speed: np.ndarray, a_max: np.ndarray
) -> np.ndarray:
    """Where a drone at ``p_next`` (..., 2) m moving at ``v_next`` (..., 2) m/s (``speed`` its
    norm, (...)) comes to rest under full braking ``a_max`` (broadcast to (...)) m/s^2:
    ``p + v |v| / (2 a_max)``, m."""
    return p_next + v_next * (speed / (2 * a_max))[..., None]


def _clip_norm(u: np.ndarray, limit: np.ndarray) -> np.ndarray:
    """Scale the rows of ``u`` ``(M, K, 2)`` that lie outside the disc of radius ``limit``
    ``(M,)`` onto its rim."""
    norm = np.linalg.norm(u, axis=-1)
    return u * np.minimum(1.0, limit[:, None] / np.maximum(norm, 1e-300))[..., None]


@dataclass
class _Incumbents:
    """The best acceleration found so far for each (drone, footprint pattern) pair: ``drone``
    ``(R,)`` planner index, ``u`` ``(R, 2)`` m/s^2, separable cost ``sep`` ``(R,)``, pattern
    ``seen`` ``(R, T)`` bool, and ``braking`` ``(R,)`` for the forced full-braking fallback."""

    drone: np.ndarray
    u: np.ndarray
    sep: np.ndarray
    seen: np.ndarray
    braking: np.ndarray


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
        self.c = 0.5 * planner.dt**2  # s^2: the next position moves by c * u
        self.p0 = self.p + self.v * planner.dt  # (M, 2) next positions with u = 0
        self.forecast = forecast
        self.z = np.asarray(forecast.positions, dtype=float)  # (T, 2)
        self.at_rest = cfg.distance_at == "rest"
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

    def evaluate(
        self, drone: np.ndarray, u: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For candidates ``u`` ``(R, K, 2)`` of drones ``drone`` ``(R,)``: the separable cost
        ``(R, K)`` (distance + effort), whether the bounds hold ``(R, K)``, and the footprint
        pattern ``(R, K, T)``."""
        planner = self.planner
        a_max = planner.max_accel[drone][:, None]  # (R, 1)
        p_next = self.p0[drone][:, None, :] + self.c * u  # (R, K, 2)
        v_next = self.v[drone][:, None, :] + planner.dt * u
        speed = np.linalg.norm(v_next, axis=-1)  # (R, K)
        rest = _rest_point(p_next, v_next, speed, a_max)
        inside = (
            (p_next >= -_EPS)
            & (p_next <= planner.upper + _EPS)
            & (rest >= -_EPS)
            & (rest <= planner.upper + _EPS)
        ).all(-1)
        ok = inside & (speed <= planner.max_speed[drone][:, None] + _EPS)
        diff = self.z[None, None, :, :] - p_next[:, :, None, :]  # (R, K, T, 2)
        reach = self.z[None, None, :, :] - rest[:, :, None, :] if self.at_rest else diff
        dist = np.sqrt((reach**2).sum(-1))
        sep = (np.maximum(dist, self.h) * self.assigned[drone][:, None, :]).sum(-1)
        sep += self.omega * np.linalg.norm(u, axis=-1)
        half = planner.half_extent[drone][:, None, None, :]
        seen = (np.abs(diff) <= half).all(-1) & self.may_see[drone][:, None, :]
        return sep, ok, seen

    def initial_candidates(self) -> np.ndarray:
        """Stage-1 accelerations ``(M, K, 2)``: zero, full braking, toward the geometric median
        of the assigned targets (exact, full and half ``max_accel``), the polar grid, and per
        target the point of its footprint box nearest to the median move and nearest to zero."""
        planner = self.planner
        a_max = planner.max_accel
        brake = _clip_norm(-self.v[:, None, :] / planner.dt, a_max)  # (M, 1, 2)
        toward = (self._geometric_median() - self.p0) / self.c  # u putting p_{t+1} on it
        norm = np.linalg.norm(toward, axis=-1, keepdims=True)
        unit = np.where(norm > 0, toward / np.maximum(norm, 1e-300), 0.0)
        # Footprint boxes in u: z_j is in view iff |p0 + c u - z_j| <= half, per axis.
        low = (self.z[None] - planner.half_extent[:, None, :] - self.p0[:, None, :]) / self.c
        high = (self.z[None] + planner.half_extent[:, None, :] - self.p0[:, None, :]) / self.c
        boxed = np.concatenate(
            [np.clip(toward[:, None, :], low, high), np.clip(0.0, low, high)], axis=1
        )  # (M, 2T, 2)
        fixed = np.stack([np.zeros_like(toward), toward, unit * a_max[:, None],
                          unit * a_max[:, None] / 2], axis=1)  # fmt: skip
        grid = a_max[:, None, None] * planner._polar[None]
        return _clip_norm(np.concatenate([brake, fixed, grid, boxed], axis=1), a_max)

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
            weight = np.maximum(wd.sum(1, keepdims=True), 1e-300)
            g = np.where(has[:, None], (wd @ self.z) / weight, g)
        return g

    def pattern_incumbents(self) -> _Incumbents:
        """Stage 1: the best admissible stage-1 candidate of every footprint pattern of every
        drone. A drone with no admissible candidate (it started where it cannot stop in the
        field) gets full braking only (candidate 0)."""
        u = self.initial_candidates()
        n_drones = len(u)
        sep, ok, seen = self.evaluate(np.arange(n_drones), u)
        braking = ~ok.any(1)
        ok[braking, 0] = True
        sep = np.where(ok, sep, np.inf)
        rows: list[tuple[int, int]] = []
        for i in range(n_drones):
            admissible = np.flatnonzero(ok[i])
            _, group = np.unique(seen[i, admissible], axis=0, return_inverse=True)
            for g in range(group.max() + 1):
                members = admissible[group.reshape(-1) == g]
                rows.append((i, int(members[np.argmin(sep[i, members])])))
        drone = np.array([i for i, _ in rows])
        k = np.array([k for _, k in rows])
        return _Incumbents(drone, u[drone, k], sep[drone, k], seen[drone, k], braking[drone])

    def refine(self, rows: _Incumbents) -> None:
        """Stage 2: pattern search on each incumbent's separable cost, keeping its footprint
        pattern and the bounds; updates ``rows`` in place. Braking fallbacks stay as they are."""
        planner = self.planner
        stencil, centre = planner._stencil, planner._centre
        index = np.arange(len(rows.drone))
        for level in range(planner.config.refinements):
            spacing = planner.max_accel[rows.drone] * 0.25 / 2**level  # (R,) m/s^2
            for _ in range(3):  # re-centre at most twice per level before refining further
                u = _clip_norm(
                    rows.u[:, None, :] + spacing[:, None, None] * stencil,
                    planner.max_accel[rows.drone],
                )  # (R, 9, 2)
                sep, ok, seen = self.evaluate(rows.drone, u)
                same = (seen == rows.seen[:, None, :]).all(-1)
                sep = np.where(ok & same & ~rows.braking[:, None], sep, np.inf)
                sep[:, centre] = rows.sep
                best = np.argmin(sep, axis=1)
                # Move only on a strict improvement, so that ties cannot oscillate.
                moved = sep[index, best] < rows.sep - 1e-12
                if not moved.any():
                    break
                rows.u[moved] = u[index, best][moved]
                rows.sep[moved] = sep[index, best][moved]

    def combine(self, rows: _Incumbents) -> np.ndarray:
        """Stage 3: one incumbent per drone minimising ``J``; returns row indices ``(M,)``."""
        n_drones = len(self.p)
        options = [np.flatnonzero(rows.drone == i) for i in range(n_drones)]
        row_bits = np.where(rows.seen, self.bit[rows.drone], 0)  # (R, T)
        columns = np.arange(len(self.z))
        if math.prod(len(o) for o in options) <= self.planner.config.max_combinations:
            grids = np.meshgrid(*options, indexing="ij")
            combos = np.stack([g.reshape(-1) for g in grids], axis=1)  # (C, M)
            masks = row_bits[combos].sum(1)  # (C, T) bits are disjoint per drone: sum = union
            cost = rows.sep[combos].sum(1) + self.alpha * self.tables[columns, masks].sum(1)
            return combos[int(np.argmin(cost))]
        choice = np.array([o[np.argmin(rows.sep[o])] for o in options])
        total = row_bits[choice].sum(0)  # (T,)
        for _ in range(self.planner.config.max_sweeps):
            changed = False
            for i, o in enumerate(options):
                others = total - row_bits[choice[i]]
                masks = others[None, :] + row_bits[o]  # (K_i, T)
                cost = rows.sep[o] + self.alpha * self.tables[columns, masks].sum(1)
                best, current = int(np.argmin(cost)), int(np.flatnonzero(o == choice[i])[0])
                # Move only on a strict improvement, so that ties cannot make sweeps cycle.
                if cost[best] < cost[current] - 1e-12:
                    choice[i] = o[best]
                    total = others + row_bits[o[best]]
                    changed = True
            if not changed:
                break
        return choice

    def result(self, u: np.ndarray) -> Plan:
        """The :class:`Plan` (with its exact cost) of accelerations ``u`` ``(M, 2)``."""
        planner = self.planner
        p_next = self.p0 + self.c * u
        diff = self.z[None, :, :] - p_next[:, None, :]  # (M, T, 2)
        if self.at_rest:
            v_next = self.v + planner.dt * u
            speed = np.linalg.norm(v_next, axis=-1)
            rest = _rest_point(p_next, v_next, speed, planner.max_accel)
            dist = np.linalg.norm(self.z[None, :, :] - rest[:, None, :], axis=-1)
        else:
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
