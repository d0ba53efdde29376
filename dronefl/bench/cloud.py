"""The cloud side of one closed-loop step in Case 3: EKF fusion and the planner.

The targets drive along their lanes at their nominal speed (a stand-in for the simulator, so that
only fusion and planning are timed); every drone reports a noisy prediction (std 1 m) of each
target inside its footprint; the drones fly the planner's accelerations. Both run in Python with
numpy on one thread (the matrices are at most 5 x 5, too small for BLAS to use threads).

The fusion reference is filterpy's ``KalmanFilter`` (if installed): one per target, the same
constant-velocity model, born at the same step, fed the same measurement stream sequentially,
with a fixed R and no gating or adaptation, so it does less work per measurement than ours
(the default ``robust`` method: consensus gating, Huber weights, adaptive R, and the forward
pass recorded for the smoother). It is timed in the same loop, on each step's measurements
right before or after our fusion (the order alternating), so that both see the same load on a
shared machine and the same caches (the planner's work between two updates leaves them cold).
"""

from __future__ import annotations

from dataclasses import replace
from time import perf_counter

import numpy as np

from dronefl.bench.results import Benchmarks
from dronefl.bench.timing import latency, with_reference
from dronefl.config import Scenario
from dronefl.planning import DroneFLPlanner, double_integrator_step
from dronefl.settings import Setting
from dronefl.sim.world import drone_start_positions
from dronefl.tracking import Fuser, FusionConfig, PositionMeasurement, cloud_fusion
from dronefl.tracking.models import ConstantVelocity
from dronefl.types import DroneState

#: Steps left out of every figure: the first updates include numpy's warm-up and track births.
WARMUP_STEPS = 10


def _start(scenario: Scenario) -> tuple[np.ndarray, np.ndarray, list[DroneState]]:
    """Targets' positions and velocities ``(N, 2)`` and the drones above their targets."""
    positions = np.array(
        [[t.start_x, scenario.field.lane_y(t.lane)] for t in scenario.targets], dtype=float
    )
    velocities = np.array(
        [[t.speed if t.heading == "east" else -t.speed, 0.0] for t in scenario.targets]
    )
    starts = drone_start_positions(scenario, positions)
    drones = [
        DroneState(d.id, start, np.zeros(2), d.altitude)
        for d, start in zip(scenario.drones, starts, strict=True)
    ]
    return positions, velocities, drones


class FilterpyFusion:
    """The filterpy reference (see module doc) over one stream: :meth:`step` takes a step's
    measurements and keeps the wall seconds it took in :attr:`seconds`."""

    def __init__(self, dt: float, config: FusionConfig) -> None:
        from filterpy.kalman import KalmanFilter

        self._kalman_filter = KalmanFilter
        self.model = config.motion_model()  # a linear one: ConstantVelocity or a subclass
        if not isinstance(self.model, ConstantVelocity):
            raise ValueError(f"the filterpy reference needs a linear motion, not {config.motion}")
        self.f = self.model.transition_matrix(dt)
        self.q = self.model.process_noise(np.zeros(4), dt)
        self.h = self.model.measurement_matrix
        self.r = config.initial_noise_std**2 * np.eye(2)
        self.initial_speed_std = config.initial_speed_std
        self.filters: dict[int, object] = {}
        self.seconds: list[float] = []

    def step(self, measurements: list[PositionMeasurement]) -> None:
        """Predict every filter one step and update it with its target's measurements, in
        drone order (a target's first measurements start its filter)."""
        started = perf_counter()
        for kf in self.filters.values():
            kf.predict()
        by_target: dict[int, list[PositionMeasurement]] = {}
        for m in measurements:
            by_target.setdefault(m.target_id, []).append(m)
        for j, group in by_target.items():
            group.sort(key=lambda m: m.drone_id)
            if j not in self.filters:
                born = np.mean([m.position for m in group], axis=0)
                mean, cov = self.model.initial(born, self.r / len(group), self.initial_speed_std)
                kf = self.filters[j] = self._kalman_filter(dim_x=4, dim_z=2)
                kf.x, kf.P, kf.F, kf.Q, kf.H = mean, cov, self.f, self.q, self.h
                continue
            for m in group:
                self.filters[j].update(m.position, R=self.r)
        self.seconds.append(perf_counter() - started)

    def states(self) -> dict[int, np.ndarray]:
        """Every target's current state ``(4,)`` (m, m/s)."""
        return {j: kf.x.copy() for j, kf in self.filters.items()}


def fly(
    scenario: Scenario,
    steps: int,
    config: FusionConfig,
    seed: int = 0,
    reference: FilterpyFusion | None = None,
) -> tuple[np.ndarray, np.ndarray, list[list[PositionMeasurement]]]:
    """Run fusion and planning for ``steps`` steps; return the wall seconds of every fusion
    update and every planner step (forecast + plan), ``(steps,)`` each, and the measurements
    of every step. ``reference``: also step it on every step's measurements, right after
    our fusion on even steps and right before it on odd ones."""
    rng = np.random.default_rng(seed)
    dt = scenario.dt
    targets, velocities, drones = _start(scenario)
    fuser = Fuser(scenario.target_ids, scenario.drone_ids, config)
    planner = DroneFLPlanner.from_scenario(scenario)
    half = planner.half_extent  # (M, 2) m, footprint half sizes
    target_ids = np.array(scenario.target_ids)
    fusion_s, plan_s, stream = np.empty(steps), np.empty(steps), []
    for step in range(steps):
        targets = targets + velocities * dt
        measurements = []
        for k, d in enumerate(drones):
            in_view = (np.abs(targets - d.position) <= half[k]).all(axis=1)
            for j, position in zip(target_ids[in_view], targets[in_view], strict=True):
                noisy = position + rng.normal(0.0, 1.0, 2)
                measurements.append(PositionMeasurement(d.drone_id, int(j), noisy))
        stream.append(measurements)
        if reference is not None and step % 2:
            reference.step(measurements)
        started = perf_counter()
        fuser.update((step + 1) * dt, measurements)
        fusion_s[step] = perf_counter() - started
        if reference is not None and not step % 2:
            reference.step(measurements)
        started = perf_counter()
        plan = planner.plan(drones, fuser.forecast(dt))
        plan_s[step] = perf_counter() - started
        drones = [
            DroneState(
                d.drone_id,
                *double_integrator_step(d.position, d.velocity, plan.accelerations[d.drone_id], dt),
                d.altitude,
                plan.accelerations[d.drone_id],
            )
            for d in drones
        ]
    return fusion_s, plan_s, stream


def filterpy_fusion(
    stream: list[list[PositionMeasurement]], dt: float, config: FusionConfig
) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """The filterpy reference on ``stream`` (see module doc): wall seconds per step ``(K,)``
    and every target's final state ``(4,)`` (m, m/s)."""
    reference = FilterpyFusion(dt, config)
    for measurements in stream:
        reference.step(measurements)
    return np.array(reference.seconds), reference.states()


def bench_cloud(scenario: Scenario, steps: int) -> Benchmarks:
    """``scenario``, ``steps`` steps (>= 20): ``fusion`` per step (ms, with the filterpy reference
    when filterpy is installed) and ``planner`` per step (forecast + plan, ms)."""
    if steps < 2 * WARMUP_STEPS:
        raise ValueError(f"steps must be >= {2 * WARMUP_STEPS}, got {steps}")
    config = cloud_fusion(Setting.load().fusion, False, scenario).fusion  # as the closed loop
    try:
        reference = FilterpyFusion(scenario.dt, config)
    except ImportError:
        reference = None  # no reference without filterpy
    fusion_s, plan_s, stream = fly(scenario, steps, config, reference=reference)
    kept = slice(WARMUP_STEPS, None)
    per_step = float(np.mean([len(m) for m in stream[kept]]))
    what = (
        f"adaptive EKF fusion ({config.method}), one {scenario.name} step "
        f"({per_step:.1f} measurements)"
    )
    fusion = replace(latency(what, fusion_s[kept], "ms", 1), measurements_per_step=per_step)
    if reference is not None:
        seconds = np.array(reference.seconds)[kept]
        what = "filterpy KalmanFilter, same stream and loop, fixed R"
        fusion = with_reference(fusion, latency(what, seconds, "ms", 1))
    what = f"DroneFL planner, one {scenario.name} step (forecast + plan)"
    planner = latency(what, plan_s[kept], "ms", 1)
    return Benchmarks(fusion=fusion, planner=planner)
