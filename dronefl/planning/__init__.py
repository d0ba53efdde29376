"""Cloud-side planning: the planner interface and the DroneFL cost-function planner (SPEC §7)."""

from dronefl.planning.base import Plan, PlanCost, Planner, double_integrator_step
from dronefl.planning.dronefl_planner import (
    DISTANCE_POINTS,
    DroneFLPlanner,
    PlannedDrone,
    PlannerConfig,
)

__all__ = [
    "DISTANCE_POINTS",
    "DroneFLPlanner",
    "Plan",
    "PlanCost",
    "PlannedDrone",
    "Planner",
    "PlannerConfig",
    "double_integrator_step",
]
