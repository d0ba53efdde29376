"""Target motion models for the cloud-side EKF (SPEC §6).

A motion model gives the discrete-time transition ``x' = f(x, dt)``, its Jacobian
``F = df/dx``, the process noise ``Q(x, dt)`` and the way a new track is born from a position.
Every model keeps the ground position ``(x, y)`` (m) in the first two state components, so every
drone's predicted target position is the linear measurement ``z = H x`` with ``H = [I_2 0]``.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

import numpy as np


def _integrated_white_noise(psd: float, dt: float) -> np.ndarray:
    """Covariance ``(2, 2)`` of (integral, value) of a white noise with PSD ``psd`` over ``dt`` s:
    ``psd * [[dt^3/3, dt^2/2], [dt^2/2, dt]]`` (the continuous white-noise-acceleration model)."""
    return psd * np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])


class MotionModel(ABC):
    """A target motion model with state dimension :attr:`ndim`; position is ``x[:2]`` in m."""

    #: State dimension ``n``.
    ndim: int

    @property
    def measurement_matrix(self) -> np.ndarray:
        """``H`` ``(2, n)``: picks the ground position ``(x, y)`` out of the state."""
        h = np.zeros((2, self.ndim))
        h[0, 0] = h[1, 1] = 1.0
        return h

    @abstractmethod
    def transition(self, x: np.ndarray, dt: float) -> np.ndarray:
        """``f(x, dt)``: the state ``(n,)`` propagated ``dt`` s ahead."""

    @abstractmethod
    def jacobian(self, x: np.ndarray, dt: float) -> np.ndarray:
        """``F = df/dx`` ``(n, n)`` evaluated at ``x``."""

    @abstractmethod
    def process_noise(self, x: np.ndarray, dt: float) -> np.ndarray:
        """``Q`` ``(n, n)``: covariance of the state error accumulated over ``dt`` s."""

    @abstractmethod
    def velocity(self, x: np.ndarray) -> np.ndarray:
        """Ground velocity ``(vx, vy)`` m/s of state ``x``."""

    @abstractmethod
    def initial(
        self, position: np.ndarray, position_covariance: np.ndarray, speed_std: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Mean ``(n,)`` and covariance ``(n, n)`` of a track born at ``position`` ``(2,)`` m
        with position covariance ``(2, 2)`` m^2 and unknown motion (speed std ``speed_std`` m/s)."""


class ConstantVelocity(MotionModel):
    r"""Nearly-constant-velocity model, state ``x = (x, y, vx, vy)`` in m and m/s.

    .. math::
        x_{k+1} = F x_k + w_k,\quad
        F = \begin{bmatrix} I_2 & \Delta t\, I_2 \\ 0 & I_2 \end{bmatrix},
        \quad Q = q \begin{bmatrix} \Delta t^3/3\, I_2 & \Delta t^2/2\, I_2 \\
        \Delta t^2/2\, I_2 & \Delta t\, I_2 \end{bmatrix}

    with ``q`` (``acceleration_psd``, m^2/s^3) the power spectral density of the white
    acceleration on each axis (Bar-Shalom et al. 2001, §6.2.2; Stone Soup's
    ``ConstantVelocity``). A vehicle whose speed changes by ``dv`` m/s over ``T`` s needs
    ``q`` of order ``dv^2 / T``.
    """

    ndim = 4

    def __init__(self, acceleration_psd: float = 0.1) -> None:
        if not (math.isfinite(acceleration_psd) and acceleration_psd > 0):
            raise ValueError(f"acceleration_psd must be > 0 m^2/s^3, got {acceleration_psd}")
        self.acceleration_psd = float(acceleration_psd)

    def transition_matrix(self, dt: float) -> np.ndarray:
        """``F`` ``(4, 4)`` for a step of ``dt`` s."""
        f = np.eye(4)
        f[0, 2] = f[1, 3] = dt
        return f

    def transition(self, x: np.ndarray, dt: float) -> np.ndarray:
        return self.transition_matrix(dt) @ x

    def jacobian(self, x: np.ndarray, dt: float) -> np.ndarray:
        return self.transition_matrix(dt)

    def process_noise(self, x: np.ndarray, dt: float) -> np.ndarray:
        (p, c), (_, v) = _integrated_white_noise(self.acceleration_psd, dt)
        # State order is (x, y, vx, vy): axis a has its position at a and its velocity at a + 2,
        # so Q = [[p, c], [c, v]] (x) I_2, written out (np.kron costs more than a predict).
        return np.array([[p, 0.0, c, 0.0], [0.0, p, 0.0, c], [c, 0.0, v, 0.0], [0.0, c, 0.0, v]])

    def velocity(self, x: np.ndarray) -> np.ndarray:
        return x[2:4]

    def initial(
        self, position: np.ndarray, position_covariance: np.ndarray, speed_std: float
    ) -> tuple[np.ndarray, np.ndarray]:
        mean = np.concatenate([position, np.zeros(2)])
        cov = np.zeros((4, 4))
        cov[:2, :2] = position_covariance
        cov[2:, 2:] = speed_std**2 * np.eye(2)
        return mean, cov


class MeanRevertingVelocity(ConstantVelocity):
    r"""Integrated Ornstein-Uhlenbeck model, state ``x = (x, y, vx, vy)`` in m and m/s: on each
    axis the velocity forgets itself over ``tau`` s, ``dv = -v / tau\, dt + \sqrt{q}\, dW``,
    so a track that no drone sees slows down instead of carrying its last velocity on (a
    vehicle whose velocity is re-drawn at random, as in Case 2). With ``a = 1 / tau`` and
    ``e = exp(-a dt)``, per axis

    .. math::
        F = \begin{bmatrix} 1 & (1 - e)/a \\ 0 & e \end{bmatrix},\quad
        Q = q \begin{bmatrix}
            \frac{dt - 2(1 - e)/a + (1 - e^2)/(2a)}{a^2} & \frac{(1 - e)^2}{2a^2} \\
            \frac{(1 - e)^2}{2a^2} & \frac{1 - e^2}{2a} \end{bmatrix}

    (Stone Soup's ``OrnsteinUhlenbeck`` with damping ``a`` and diffusion ``q``; a test checks
    it). The stationary speed std per axis is ``sqrt(q tau / 2)``; as ``tau -> inf`` the model
    becomes :class:`ConstantVelocity` with the same ``q``.
    """

    def __init__(self, acceleration_psd: float = 0.1, velocity_time_constant: float = 1.0) -> None:
        super().__init__(acceleration_psd)
        tau = velocity_time_constant
        if not (math.isfinite(tau) and tau > 0):
            raise ValueError(f"velocity_time_constant must be > 0 s, got {tau}")
        self.velocity_time_constant = float(tau)

    def transition_matrix(self, dt: float) -> np.ndarray:
        a = 1.0 / self.velocity_time_constant
        e = math.exp(-a * dt)
        f = np.eye(4)
        f[0, 2] = f[1, 3] = -math.expm1(-a * dt) / a
        f[2, 2] = f[3, 3] = e
        return f

    def process_noise(self, x: np.ndarray, dt: float) -> np.ndarray:
        a, q = 1.0 / self.velocity_time_constant, self.acceleration_psd
        one_e = -math.expm1(-a * dt)  # 1 - e, without cancellation for small a dt
        one_e2 = -math.expm1(-2.0 * a * dt)  # 1 - e^2
        p = q * (dt - 2.0 * one_e / a + one_e2 / (2.0 * a)) / a**2
        c = q * one_e**2 / (2.0 * a**2)
        v = q * one_e2 / (2.0 * a)
        return np.array([[p, 0.0, c, 0.0], [0.0, p, 0.0, c], [c, 0.0, v, 0.0], [0.0, c, 0.0, v]])


class CoordinatedTurn(MotionModel):
    r"""Nonlinear coordinated-turn model, state ``x = (x, y, v, psi, omega)``: position m, speed
    m/s, heading rad (counter-clockwise from east) and turn rate rad/s.

    .. math::
        x' = x + \frac{v}{\omega}\left(\sin(\psi + \omega\Delta t) - \sin\psi\right),\quad
        y' = y + \frac{v}{\omega}\left(\cos\psi - \cos(\psi + \omega\Delta t)\right),\quad
        v' = v,\ \psi' = \psi + \omega \Delta t,\ \omega' = \omega

    (the CTRV model, e.g. Schubert et al. 2008). For ``|omega| < 1e-4`` rad/s the arcs are
    replaced by their second-order expansion in ``omega`` (error below 1e-12 m at the speeds
    and steps used here), which keeps ``f`` and ``F`` smooth through ``omega = 0``.

    Process noise: white along-track acceleration (PSD ``acceleration_psd``, m^2/s^3) drives
    the along-track position and ``v``; white turn acceleration (PSD ``turn_rate_psd``,
    rad^2/s^3) drives ``psi`` and ``omega``; each pair gets the integrated-white-noise block
    ``psd [[dt^3/3, dt^2/2], [dt^2/2, dt]]``, the position part along ``(cos psi, sin psi)``.
    """

    ndim = 5
    _SMALL_TURN = 1e-4  # rad/s

    def __init__(
        self,
        acceleration_psd: float = 0.1,
        turn_rate_psd: float = 0.01,
        initial_turn_rate_std: float = 0.1,
    ) -> None:
        for name, value in (
            ("acceleration_psd", acceleration_psd),
            ("turn_rate_psd", turn_rate_psd),
            ("initial_turn_rate_std", initial_turn_rate_std),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive finite number, got {value}")
        self.acceleration_psd = float(acceleration_psd)
        self.turn_rate_psd = float(turn_rate_psd)
        self.initial_turn_rate_std = float(initial_turn_rate_std)

    def transition(self, x: np.ndarray, dt: float) -> np.ndarray:
        px, py, v, psi, omega = x
        s0, c0 = math.sin(psi), math.cos(psi)
        if abs(omega) < self._SMALL_TURN:
            dx = v * dt * c0 - 0.5 * v * dt**2 * omega * s0
            dy = v * dt * s0 + 0.5 * v * dt**2 * omega * c0
        else:
            s1, c1 = math.sin(psi + omega * dt), math.cos(psi + omega * dt)
            dx = v / omega * (s1 - s0)
            dy = v / omega * (c0 - c1)
        return np.array([px + dx, py + dy, v, psi + omega * dt, omega])

    def jacobian(self, x: np.ndarray, dt: float) -> np.ndarray:
        _, _, v, psi, omega = x
        s0, c0 = math.sin(psi), math.cos(psi)
        f = np.eye(5)
        if abs(omega) < self._SMALL_TURN:
            f[0, 2] = dt * c0 - 0.5 * dt**2 * omega * s0
            f[0, 3] = -v * dt * s0 - 0.5 * v * dt**2 * omega * c0
            f[0, 4] = -0.5 * v * dt**2 * s0
            f[1, 2] = dt * s0 + 0.5 * dt**2 * omega * c0
            f[1, 3] = v * dt * c0 - 0.5 * v * dt**2 * omega * s0
            f[1, 4] = 0.5 * v * dt**2 * c0
        else:
            s1, c1 = math.sin(psi + omega * dt), math.cos(psi + omega * dt)
            f[0, 2] = (s1 - s0) / omega
            f[0, 3] = v / omega * (c1 - c0)
            f[0, 4] = v * dt * c1 / omega - v / omega**2 * (s1 - s0)
            f[1, 2] = (c0 - c1) / omega
            f[1, 3] = v / omega * (s1 - s0)
            f[1, 4] = v * dt * s1 / omega - v / omega**2 * (c0 - c1)
        f[3, 4] = dt
        return f

    def process_noise(self, x: np.ndarray, dt: float) -> np.ndarray:
        psi = x[3]
        along = np.array([math.cos(psi), math.sin(psi)])
        speed = _integrated_white_noise(self.acceleration_psd, dt)
        q = np.zeros((5, 5))
        q[:2, :2] = speed[0, 0] * np.outer(along, along)
        q[:2, 2] = q[2, :2] = speed[0, 1] * along
        q[2, 2] = speed[1, 1]
        q[3:, 3:] = _integrated_white_noise(self.turn_rate_psd, dt)
        return q

    def velocity(self, x: np.ndarray) -> np.ndarray:
        return x[2] * np.array([math.cos(x[3]), math.sin(x[3])])

    def initial(
        self, position: np.ndarray, position_covariance: np.ndarray, speed_std: float
    ) -> tuple[np.ndarray, np.ndarray]:
        # Heading is unknown: psi = 0 with a std of pi; a negative v then encodes westward motion
        # until the heading has been learnt.
        mean = np.array([position[0], position[1], 0.0, 0.0, 0.0])
        cov = np.zeros((5, 5))
        cov[:2, :2] = position_covariance
        cov[2, 2] = speed_std**2
        cov[3, 3] = math.pi**2
        cov[4, 4] = self.initial_turn_rate_std**2
        return mean, cov
