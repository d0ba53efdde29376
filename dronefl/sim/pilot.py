"""The scripted pilot used to record training data (the paper's "manually controlled" drones).

Each drone is steered over the centre of the bounding box of its assigned targets' true
positions ``c`` with a critically damped PD law on position and velocity error,

    u = k_p (c - p) + k_d (c_dot - v),

then saturated by the dynamics. With ``k_p = 0.5 s^-2`` and ``k_d = 1.4 s^-1`` the closed loop
has natural frequency 0.71 rad/s and damping ratio 0.99.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dronefl.sim.world import World


@dataclass(frozen=True)
class PilotController:
    """Keeps every drone above its assigned targets (gains in s^-2 and s^-1)."""

    kp: float = 0.5
    kd: float = 1.4

    def control(self, world: World) -> np.ndarray:
        """Horizontal acceleration commands ``(M, 2)`` m/s^2 for the current world state."""
        column = {int(i): j for j, i in enumerate(world.targets.ids)}
        commands = np.zeros((len(world.drones.ids), 2))
        for k, spec in enumerate(world.scenario.drones):
            cols = [column[i] for i in spec.targets]
            pts = world.targets.position[cols]
            centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
            centre_velocity = world.targets.velocity[cols].mean(axis=0)
            commands[k] = self.kp * (centre - world.drones.position[k]) + self.kd * (
                centre_velocity - world.drones.velocity[k]
            )
        return commands
