"""Planner interface: drone states and the fused tracks in, one acceleration per drone out."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dronefl.tracking.fusion import TrackForecast
from dronefl.types import DroneState


@dataclass(frozen=True)
class PlanCost:
    """The terms of the planning cost ``J`` (SPEC §7) for one step: ``distance`` (m, the sum of
    ``max(||p_i - z_j||, h)`` over assigned pairs), ``uncertainty`` (``alpha sum_j Tr P_j``),
    ``effort`` (``omega sum_i ||u_i||``) and their sum ``total``."""

    distance: float
    uncertainty: float
    effort: float

    @property
    def total(self) -> float:
        return self.distance + self.uncertainty + self.effort


@dataclass(frozen=True)
class Plan:
    """One planning step's decision.

    ``accelerations``: ``{drone_id: (2,)}`` horizontal acceleration command, m/s^2;
    ``positions``: ``{drone_id: (2,)}`` the next positions they lead to, m; ``observers``:
    ``{target_id: drone ids}`` whose camera footprint at its next position holds the target;
    ``cost``: the :class:`PlanCost` of this decision.
    """

    accelerations: dict[int, np.ndarray]
    positions: dict[int, np.ndarray]
    observers: dict[int, tuple[int, ...]]
    cost: PlanCost


def double_integrator_step(
    position: np.ndarray, velocity: np.ndarray, acceleration: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """``p' = p + v dt + u dt^2 / 2``, ``v' = v + u dt`` (arrays ``(..., 2)`` in m, m/s, m/s^2):
    the paper's ``p_{t+1} = Phi p_t + Lambda u_t`` for constant acceleration over ``dt`` s."""
    return position + velocity * dt + 0.5 * dt**2 * acceleration, velocity + acceleration * dt


class Planner(ABC):
    """Chooses every drone's acceleration for the next step (centralised, in the cloud)."""

    @abstractmethod
    def plan(self, drones: Sequence[DroneState], forecast: TrackForecast) -> Plan:
        """Accelerations for ``drones`` given the fused tracks' ``forecast``."""

    def state(self) -> object:
        """What the planner carries from one step to the next, as plain Python and numpy
        objects, for an episode checkpoint; ``None`` (the default): nothing. A planner that
        keeps anything between steps (a warm start, a random generator) overrides this and
        :meth:`restore`, so that a resumed episode continues bit-identically."""
        return None

    def restore(self, state: object) -> None:
        """Continue from ``state``, a :meth:`state` of a planner built the same way."""
        if state is not None:
            raise ValueError(f"{type(self).__name__} carries no state to restore, got {state!r}")
