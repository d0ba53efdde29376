"""The cloud's half of the closed loop (paper Fig. 3): fuse -> plan -> label.

:class:`CloudNode` is the same object in ``dronefl track`` (stepped in one process) and in a
deployed cloud (the ServerApp of ``dronefl cloud``, which feeds it what arrives over Zenoh).
Each step it fuses the predictions that reached it (one adaptive EKF per target, the filters
:func:`~dronefl.tracking.fusion.cloud_fusion` makes of the setting) and plans every drone's
acceleration; at an FL round it makes each drone's pseudo-labels from the fused tracks of
the whole past (:meth:`CloudNode.labels`). How the models learn from them is the method's
(:data:`dronefl.learners.LEARNERS`), and how the rounds travel is the runner's.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from dronefl.config import Scenario
from dronefl.planning import PlannerConfig
from dronefl.planning.base import Plan, Planner
from dronefl.settings import Setting
from dronefl.tracking import Fuser, FusionConfig, PositionMeasurement, Track, make_labels
from dronefl.tracking.fusion import CloudFusion, cloud_fusion, planner_forecast, update_filters
from dronefl.tracking.labels import drone_labels
from dronefl.types import DroneState

#: Makes the cloud's fusion: ``(scenario, fusion settings) -> Fuser``.
FuserFactory = Callable[[Scenario, FusionConfig], Fuser]
#: Makes the cloud's planner: ``(scenario, planner settings) -> Planner``.
PlannerFactory = Callable[[Scenario, PlannerConfig], Planner]


def scenario_fuser(scenario: Scenario, config: FusionConfig) -> Fuser:
    """The cloud's fusion for ``scenario``: one EKF per target, with ``config``."""
    return Fuser(scenario.target_ids, scenario.drone_ids, config)


@dataclass(frozen=True)
class Received:
    """The predictions of drone ``drone_id`` that reached the cloud at one step:
    ``target_ids``, ``positions`` ``(n, 2)`` m and the noise it reported, ``(2, 2)`` m² by
    target id."""

    drone_id: int
    target_ids: tuple[int, ...]
    positions: np.ndarray
    reports: Mapping[int, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True)
class Fused:
    """One step's fusion: ``tracks``, the planner's tracks of every target that has one, and
    ``fused``, those of the filter whose ``Tr P`` the planner weighs and whose history gives
    the labels (the same dict with one filter)."""

    tracks: dict[int, Track]
    fused: dict[int, Track]


class CloudNode:
    """The cloud's fusion, planning and pseudo-labels for ``scenario`` as ``setting`` says,
    with the fusion and the planner made by ``fuser`` and ``planner`` (a study's own parts;
    the defaults are DroneFL's)."""

    def __init__(
        self,
        scenario: Scenario,
        setting: Setting,
        fuser: FuserFactory = scenario_fuser,
        planner: PlannerFactory | None = None,
    ) -> None:
        from dronefl.planning import DroneFLPlanner

        self.scenario, self.setting = scenario, setting
        self.filters: CloudFusion = cloud_fusion(
            setting.fusion, setting.drone.noise_reports, scenario
        )
        # The planner's tracks; with a q of their own the labels have a filter of their own.
        self.fuser = fuser(scenario, self.filters.tracks)
        self.label_fuser = (
            None if self.filters.planner is None else fuser(scenario, self.filters.fusion)
        )
        make_planner = planner or DroneFLPlanner.from_scenario
        self.planner = make_planner(
            scenario, PlannerConfig(distance_at=setting.planner.distance_at)
        )
        self.planner_seconds = 0.0
        self.column = {t: j for j, t in enumerate(scenario.target_ids)}

    def fuse(self, t: float, received: Sequence[Received]) -> Fused:
        """Fuse the predictions ``received`` (in drone order) of time ``t`` s; a target id the
        scenario does not know is ignored."""
        measurements = [
            PositionMeasurement(r.drone_id, target_id, position, r.reports.get(target_id))
            for r in received
            for target_id, position in zip(r.target_ids, r.positions, strict=True)
            if target_id in self.column
        ]
        tracks, fused = update_filters(self.fuser, self.label_fuser, t, measurements)
        return Fused(tracks, fused)

    def plan(self, drones: Sequence[DroneState], fused: Fused) -> Plan:
        """Every drone's acceleration for the next step (:attr:`planner_seconds` counts the
        time spent)."""
        started = time.perf_counter()
        forecast = planner_forecast(self.fuser, self.label_fuser, fused.tracks, self.scenario.dt)
        plan = self.planner.plan(drones, forecast)
        self.planner_seconds += time.perf_counter() - started
        return plan

    def labels(
        self, t: np.ndarray, received: np.ndarray, truth: np.ndarray | None = None
    ) -> np.ndarray:
        """Each drone's training labels ``(M, T, N, 2)`` m for the steps of ``t`` ``(T,)`` s
        (the whole past), NaN where it has none: the fused tracks as ``learning.labels`` makes
        them (:func:`~dronefl.tracking.make_labels`; the truth ``(T, N, 2)`` m for the
        ``ground_truth`` ablation), for the drones ``learning.label_drones`` names given the
        predictions ``received`` ``(>= T, M, N, 2)`` m (NaN where none reached the cloud)."""
        learning = self.setting.learning
        labelled = self.fuser if self.label_fuser is None else self.label_fuser
        labels = make_labels(learning.labels, labelled, t, truth=truth)
        assigned = self.scenario.assignment() if self.setting.drone.detected_only else None
        return drone_labels(labels.position, received, learning.label_drones, assigned)

    @property
    def rejections(self) -> int:
        """Measurements the planner's filter gated out so far."""
        return int(self.fuser.rejections)

    @property
    def resets(self) -> int:
        """Tracks the planner's filter re-initialised so far."""
        return int(self.fuser.resets)
