"""Drones: horizontal double integrators at fixed altitudes, with noisy 12-dim odometry.

With state ``(p, v)`` (m, m/s) and commanded acceleration ``u`` (m/s^2), one step of ``dt`` s is

    v' = sat_vmax(v + sat_amax(u) dt),     p' = clip_field(p + (v + v') dt / 2)

i.e. ``p' = Phi p + Lambda u`` of the paper with speed and acceleration bounds; where the drone
would leave the field it stops at the edge and its outward velocity is zeroed. Roll and pitch
are those a quadrotor needs to produce ``u`` (``pitch = atan(a_x / g)``, ``roll =
-atan(a_y / g)``); the camera is gimbal-stabilised and always points straight down, yaw 0.
"""

from __future__ import annotations

import numpy as np

from dronefl.config import Scenario
from dronefl.types import ODOMETRY_DIM, DroneState, Odometry

GRAVITY = 9.81  # m/s^2


def saturate(vectors: np.ndarray, limits: np.ndarray) -> np.ndarray:
    """Scale each row of ``vectors`` ``(M, 2)`` down to norm at most ``limits`` ``(M,)``."""
    norms = np.linalg.norm(vectors, axis=-1)
    scale = np.minimum(1.0, limits / np.maximum(norms, 1e-12))
    return vectors * scale[:, None]


class DroneTeam:
    """All drones of a scenario, stepped together (arrays indexed in scenario order)."""

    def __init__(self, scenario: Scenario, start: np.ndarray, rng: np.random.Generator) -> None:
        self.scenario = scenario
        self.ids = np.array(scenario.drone_ids)
        self.altitude = np.array([d.altitude for d in scenario.drones], dtype=float)
        self.max_speed = np.array([d.max_speed for d in scenario.drones], dtype=float)
        self.max_accel = np.array([d.max_accel for d in scenario.drones], dtype=float)
        self.position = np.array(start, dtype=float).reshape(len(self.ids), 2)
        self.velocity = np.zeros_like(self.position)
        self.acceleration = np.zeros_like(self.position)
        self._attitude = np.zeros((len(self.ids), 3))
        self._rates = np.zeros((len(self.ids), 3))
        self.rng = rng

    def step(self, command: np.ndarray, dt: float) -> None:
        """Apply horizontal accelerations ``command`` ``(M, 2)`` m/s^2 for ``dt`` s."""
        command = np.asarray(command, dtype=float).reshape(self.position.shape)
        if not np.isfinite(command).all():
            raise ValueError("drone command holds NaN or inf values")
        u = saturate(command, self.max_accel)
        v_new = saturate(self.velocity + u * dt, self.max_speed)
        p_new = self.position + 0.5 * (self.velocity + v_new) * dt
        field = self.scenario.field
        upper = np.array([field.width, field.height])
        outside_low, outside_high = p_new < 0.0, p_new > upper
        p_new = np.clip(p_new, 0.0, upper)
        v_new[outside_low & (v_new < 0)] = 0.0
        v_new[outside_high & (v_new > 0)] = 0.0
        self.acceleration = (v_new - self.velocity) / dt
        self.position, self.velocity = p_new, v_new
        attitude = np.stack(
            [
                -np.arctan(self.acceleration[:, 1] / GRAVITY),
                np.arctan(self.acceleration[:, 0] / GRAVITY),
                np.zeros(len(self.ids)),
            ],
            axis=-1,
        )
        self._rates = (attitude - self._attitude) / dt
        self._attitude = attitude

    def state(self) -> dict:
        """Everything that changes as the drones fly (arrays and the odometry noise's random
        generator state), for an episode checkpoint; :meth:`restore` takes it back."""
        return {
            "position": self.position.copy(), "velocity": self.velocity.copy(),
            "acceleration": self.acceleration.copy(), "attitude": self._attitude.copy(),
            "rates": self._rates.copy(), "rng": self.rng.bit_generator.state,
        }  # fmt: skip

    def restore(self, state: dict) -> None:
        """Continue from ``state`` (:meth:`state` of a team of the same scenario)."""
        self.position, self.velocity = state["position"].copy(), state["velocity"].copy()
        self.acceleration = state["acceleration"].copy()
        self._attitude, self._rates = state["attitude"].copy(), state["rates"].copy()
        self.rng.bit_generator.state = state["rng"]

    def camera_positions(self) -> np.ndarray:
        """Camera centres ``(M, 3)`` m."""
        return np.concatenate([self.position, self.altitude[:, None]], axis=-1)

    def odometry(self, t: float) -> list[Odometry]:
        """Noisy 12-dim odometry of every drone at time ``t`` (s)."""
        noise = self.scenario.odometry_noise
        m = len(self.ids)
        truth = np.concatenate(
            [
                self.camera_positions(),
                np.concatenate([self.velocity, np.zeros((m, 1))], axis=-1),
                self._attitude,
                self._rates,
            ],
            axis=-1,
        )
        std = np.repeat([noise.position, noise.velocity, noise.attitude, noise.rate], 3)
        measured = truth + self.rng.normal(0.0, 1.0, size=(m, ODOMETRY_DIM)) * std
        return [Odometry(t, measured[i]) for i in range(m)]

    def states(self) -> tuple[DroneState, ...]:
        """Current true states, in scenario order."""
        return tuple(
            DroneState(
                int(i),
                self.position[k].copy(),
                self.velocity[k].copy(),
                float(self.altitude[k]),
                self.acceleration[k].copy(),
            )
            for k, i in enumerate(self.ids)
        )
