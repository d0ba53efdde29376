"""The scripted pilot used to record training data (the paper's "manually controlled" drones).

Each drone is steered towards an aim point ``a = c + w`` with a critically damped PD law,

    u = k_p (a - p) + k_d (c_dot - v),

where ``c`` is the centre of the bounding box of its assigned targets' true positions and ``w``
a slowly wandering offset, as a human pilot's: per axis an Ornstein-Uhlenbeck process with time
constant ``wander_tau`` s and standard deviation ``wander`` times the camera footprint's half
extent, clipped so that every assigned target stays ``margin`` m inside the footprint. Without
the wander the targets would sit at the image centre in every frame and a predictor trained on
such data never learns how box position maps to ground position. With ``k_p = 0.5 s^-2`` and
``k_d = 1.4 s^-1`` the loop has natural frequency 0.71 rad/s and damping ratio 0.99.
"""

from __future__ import annotations

import math

import numpy as np

from dronefl.sim.world import World


class PilotController:
    """Keeps every drone above its assigned targets, wandering like a human pilot."""

    def __init__(
        self,
        rng: np.random.Generator | None = None,
        kp: float = 0.5,
        kd: float = 1.4,
        wander: float = 0.5,
        wander_tau: float = 20.0,
        margin: float = 4.0,
    ) -> None:
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.kp, self.kd = kp, kd
        self.wander, self.wander_tau, self.margin = wander, wander_tau, margin
        self._offset: np.ndarray | None = None  # (M, 2) unit-variance OU state

    def control(self, world: World) -> np.ndarray:
        """Horizontal acceleration commands ``(M, 2)`` m/s^2 for the current world state."""
        m = len(world.drones.ids)
        if self._offset is None:
            self._offset = self.rng.normal(size=(m, 2))
        decay = math.exp(-world.dt / self.wander_tau)
        noise = self.rng.normal(size=(m, 2)) * math.sqrt(1 - decay**2)
        self._offset = decay * self._offset + noise
        column = {int(i): j for j, i in enumerate(world.targets.ids)}
        commands = np.zeros((m, 2))
        for k, spec in enumerate(world.scenario.drones):
            pts = world.targets.position[[column[i] for i in spec.targets]]
            lo, hi = pts.min(axis=0), pts.max(axis=0)
            centre = 0.5 * (lo + hi)
            half = np.array(world.camera.footprint_half_extent(spec.altitude))
            room = np.maximum(half - 0.5 * (hi - lo) - self.margin, 0.0)
            aim = centre + np.clip(self.wander * half * self._offset[k], -room, room)
            centre_velocity = world.targets.velocity[[column[i] for i in spec.targets]].mean(0)
            commands[k] = self.kp * (aim - world.drones.position[k]) + self.kd * (
                centre_velocity - world.drones.velocity[k]
            )
        return commands
