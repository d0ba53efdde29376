"""Multi-drone fusion in the cloud: one adaptive EKF per target fed by every drone's predictions.

Each step the drones send their predicted positions of the targets they see
(:class:`PositionMeasurement`); :meth:`Fuser.update` propagates every track to the time those
predictions refer to, fuses them (sequentially, in drone-id order, each with its pair's adapted
``R``, gated), and returns the fused :class:`Track` of every target. A target that nobody
reports is only predicted. :meth:`Fuser.forecast` hands the planner a :class:`TrackForecast`:
the fused positions and, for any set of observing drones, the trace of the covariance after the
next predict + update.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from dronefl.tracking.adaptive import AdaptiveMeasurementNoise
from dronefl.tracking.ekf import CHI2_2DOF_99, ExtendedKalmanFilter
from dronefl.tracking.models import ConstantVelocity, CoordinatedTurn, MotionModel


@dataclass(frozen=True)
class FusionConfig:
    """Settings of the cloud fusion (SPEC §6).

    ``motion``: ``constant_velocity`` (x, y, vx, vy) or ``coordinated_turn`` (x, y, v, psi, omega).
    ``acceleration_psd``: white-acceleration PSD q, m^2/s^3 (0.5 m/s vehicles turning at the
    headlands need ~0.01-0.1; the random-walk targets of Case 2 change velocity by ~1 m/s each
    second and need ~1). ``turn_rate_psd``: turn-acceleration PSD of the coordinated-turn model,
    rad^2/s^3. ``initial_noise_std``: std of every pair's starting ``R = sigma^2 I``, m.
    ``initial_speed_std``: velocity std of a newborn track, m/s. ``adaptive``: adapt ``R`` per
    pair (off: ``R`` stays at its initial value). ``adaptation_rate``: EMA rate ``beta`` per
    accepted update. ``noise_floor_std``: ``R``'s smallest allowed std, m. ``gate``: squared
    Mahalanobis threshold (chi-square 2 dof 99 % by default), ``None`` disables gating.
    ``reset_after``: re-initialise a track from the measurements when every measurement of it was
    gated out on this many consecutive updates (a lost track cannot recover through the gate),
    ``None`` never.
    """

    motion: Literal["constant_velocity", "coordinated_turn"] = "constant_velocity"
    acceleration_psd: float = 0.1
    turn_rate_psd: float = 0.01
    initial_noise_std: float = 1.0
    initial_speed_std: float = 1.0
    adaptive: bool = True
    adaptation_rate: float = 0.02
    noise_floor_std: float = 0.05
    gate: float | None = CHI2_2DOF_99
    reset_after: int | None = 5

    def __post_init__(self) -> None:
        if self.motion not in ("constant_velocity", "coordinated_turn"):
            raise ValueError(
                f"motion: unknown model {self.motion!r} (constant_velocity, coordinated_turn)"
            )
        for name in (
            "acceleration_psd",
            "turn_rate_psd",
            "initial_noise_std",
            "initial_speed_std",
            "noise_floor_std",
        ):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: must be a positive finite number, got {value!r}")
        if not 0 < self.adaptation_rate <= 1:
            raise ValueError(f"adaptation_rate: must be in (0, 1], got {self.adaptation_rate}")
        if self.gate is not None and not self.gate > 0:
            raise ValueError(f"gate: must be > 0 (squared Mahalanobis distance), got {self.gate}")
        if self.reset_after is not None and self.reset_after < 1:
            raise ValueError(f"reset_after: must be >= 1 update or None, got {self.reset_after}")

    def motion_model(self) -> MotionModel:
        """The configured :class:`MotionModel`."""
        if self.motion == "coordinated_turn":
            return CoordinatedTurn(self.acceleration_psd, self.turn_rate_psd)
        return ConstantVelocity(self.acceleration_psd)


@dataclass(frozen=True)
class PositionMeasurement:
    """Drone ``drone_id``'s predicted ground ``position`` ``(2,)`` (m, world frame) of target
    ``target_id``; the time it refers to is the ``t`` of the :meth:`Fuser.update` call."""

    drone_id: int
    target_id: int
    position: np.ndarray


@dataclass(frozen=True)
class Track:
    """The fused estimate of one target at time ``t`` (s).

    ``mean`` ``(n,)`` and ``covariance`` ``(n, n)`` in the motion model's state (position first,
    m); ``accepted`` / ``rejected`` count this update's fused and gated-out measurements.
    """

    target_id: int
    t: float
    mean: np.ndarray
    covariance: np.ndarray
    velocity: np.ndarray
    accepted: int = 0
    rejected: int = 0

    @property
    def position(self) -> np.ndarray:
        """Fused ground position ``(2,)``, m."""
        return self.mean[:2]

    @property
    def position_covariance(self) -> np.ndarray:
        """Position covariance ``(2, 2)``, m^2."""
        return self.covariance[:2, :2]


class TrackForecast:
    r"""What the planner needs from fusion at one instant (all arrays in :attr:`target_ids` order).

    ``positions`` ``(T, 2)`` m: the fused target positions ``z_j``. For target ``j`` the
    covariance after one more predict step, ``P^-_j = F P_j F^T + Q`` ``(n, n)``, and the noise
    ``R_ij`` of each drone ``i`` in :attr:`drone_ids` give the covariance after the updates of a set
    ``A`` of observing drones in information form,

    .. math::
        \Lambda_A = \sum_{i \in A} R_{ij}^{-1},\qquad
        P^+_j(A) = P^-_j - B_j S_A^{-1} B_j^T,\qquad
        S_A^{-1} = (I + \Lambda_A\, H P^-_j H^T)^{-1} \Lambda_A,\quad B_j = P^-_j H^T

    which equals the sequential Kalman updates (independent position measurements combine to one
    with noise ``Lambda_A^{-1}``) and needs only ``2 x 2`` inverses, even for ``A`` empty.
    """

    def __init__(
        self,
        target_ids: tuple[int, ...],
        drone_ids: tuple[int, ...],
        positions: np.ndarray,
        predicted_covariances: np.ndarray,
        noise_covariances: np.ndarray,
    ) -> None:
        t, d = len(target_ids), len(drone_ids)
        if positions.shape != (t, 2):
            raise ValueError(f"positions must be ({t}, 2), got {positions.shape}")
        if noise_covariances.shape != (d, t, 2, 2):
            raise ValueError(f"noise covariances must be ({d}, {t}, 2, 2)")
        self.target_ids = target_ids
        self.drone_ids = drone_ids
        self.positions = positions
        self.predicted_covariances = predicted_covariances  # (T, n, n)
        self._prior_trace = np.trace(predicted_covariances, axis1=1, axis2=2)  # (T,)
        self._a = predicted_covariances[:, :2, :2]  # H P^- H^T, (T, 2, 2)
        b = predicted_covariances[:, :, :2]  # P^- H^T, (T, n, 2)
        self._btb = np.einsum("tni,tnj->tij", b, b)  # B^T B, (T, 2, 2)
        self._info = np.linalg.inv(noise_covariances)  # R^-1, (D, T, 2, 2)

    def trace_table(self, target_index: int, drone_indices: Sequence[int]) -> np.ndarray:
        """``Tr P^+`` (m^2, plus velocity terms) for every subset of ``drone_indices`` (indices into
        :attr:`drone_ids`), ``(2^k,)``: entry ``m`` uses the drones whose bit is set in ``m``
        (bit ``b`` = ``drone_indices[b]``)."""
        k = len(drone_indices)
        bits = (np.arange(2**k)[:, None] >> np.arange(k)) & 1  # (2^k, k)
        info = self._info[list(drone_indices), target_index].reshape(k, 4)
        lam = (bits @ info).reshape(-1, 2, 2)  # Lambda_A, (2^k, 2, 2)
        m = np.eye(2) + lam @ self._a[target_index]
        s_inv = _inv2(m) @ lam  # S_A^-1, (2^k, 2, 2)
        reduction = np.einsum("mij,ji->m", s_inv, self._btb[target_index])  # Tr(S^-1 B^T B)
        return self._prior_trace[target_index] - reduction

    def trace_after(self, target_id: int, drone_ids: Sequence[int]) -> float:
        """``Tr P^+`` of target ``target_id`` after updates from ``drone_ids`` (may be empty)."""
        j = self.target_ids.index(target_id)
        idx = [self.drone_ids.index(i) for i in drone_ids]
        return float(self.trace_table(j, idx)[-1])


def _inv2(m: np.ndarray) -> np.ndarray:
    """Closed-form inverse of a stack of ``(..., 2, 2)`` matrices."""
    det = m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] * m[..., 1, 0]
    inv = np.empty_like(m)
    inv[..., 0, 0] = m[..., 1, 1]
    inv[..., 1, 1] = m[..., 0, 0]
    inv[..., 0, 1] = -m[..., 0, 1]
    inv[..., 1, 0] = -m[..., 1, 0]
    return inv / det[..., None, None]


class Fuser:
    r"""Cloud-side fusion of every drone's target predictions (SPEC §6).

    One :class:`ExtendedKalmanFilter` per target ``j`` and one :class:`AdaptiveMeasurementNoise`
    ``R_ij`` per (drone, target) pair. An update at time ``t`` predicts every track from the
    previous update to ``t``, then, for each drone ``i`` that reported ``j`` (in drone-id
    order), applies the gated EKF update with ``z_ij`` and ``R_ij``:

    .. math::
        d^2_{ij} = y_{ij}^T S_{ij}^{-1} y_{ij} \le \text{gate} \Rightarrow
        x_j \leftarrow x_j + K y_{ij},\ P_j \leftarrow (I - KH) P_j (I - KH)^T + K R_{ij} K^T,\
        R_{ij} \leftarrow \text{EMA}(y_{ij} y_{ij}^T - H P_j^- H^T)

    Sequential updates with independent noises equal one joint update with the stacked
    measurement; each innovation is taken against the estimate the earlier drones left, which is
    also the prior the adaptation of ``R_ij`` needs.

    ``target_ids`` / ``drone_ids``: the scenario's ids; ``config``: :class:`FusionConfig`;
    ``initial_positions``: optional ``{target_id: (2,)}`` m to start tracks at ``t0`` (with
    position std ``initial_noise_std``); other targets get a track at their first measurement
    (the mean of that step's positions). Counters: :attr:`rejections` (gated-out measurements),
    :attr:`resets` (tracks re-initialised after ``reset_after`` all-rejected updates),
    :attr:`dropped` (non-finite measurements ignored).
    """

    def __init__(
        self,
        target_ids: Sequence[int],
        drone_ids: Sequence[int],
        config: FusionConfig | None = None,
        initial_positions: Mapping[int, np.ndarray] | None = None,
        t0: float = 0.0,
    ) -> None:
        self.config = config or FusionConfig()
        self.target_ids = tuple(int(j) for j in target_ids)
        self.drone_ids = tuple(int(i) for i in drone_ids)
        if len(set(self.target_ids)) != len(self.target_ids) or not self.target_ids:
            raise ValueError(f"target_ids must be non-empty and unique, got {self.target_ids}")
        if len(set(self.drone_ids)) != len(self.drone_ids) or not self.drone_ids:
            raise ValueError(f"drone_ids must be non-empty and unique, got {self.drone_ids}")
        self.model = self.config.motion_model()
        self.t = float(t0)
        r0 = self.config.initial_noise_std**2 * np.eye(2)
        floor = self.config.noise_floor_std**2
        self._noise = {
            (i, j): AdaptiveMeasurementNoise(
                r0, self.config.adaptation_rate, floor, self.config.gate
            )
            for i in self.drone_ids
            for j in self.target_ids
        }
        self._filters: dict[int, ExtendedKalmanFilter] = {}
        self._misses = dict.fromkeys(self.target_ids, 0)
        self._last: dict[int, tuple[int, int]] = {}
        self.rejections = 0
        self.resets = 0
        self.dropped = 0
        for j, position in (initial_positions or {}).items():
            if j not in self.target_ids:
                raise ValueError(f"initial_positions: unknown target {j}")
            self._filters[j] = self._new_filter(np.asarray(position, dtype=float), r0)

    def _new_filter(
        self, position: np.ndarray, position_covariance: np.ndarray
    ) -> ExtendedKalmanFilter:
        if position.shape != (2,) or not np.isfinite(position).all():
            raise ValueError(f"a track needs a finite (2,) position, got {position}")
        mean, cov = self.model.initial(position, position_covariance, self.config.initial_speed_std)
        return ExtendedKalmanFilter(self.model, mean, cov, gate=self.config.gate)

    def measurement_noise(self, drone_id: int, target_id: int) -> np.ndarray:
        """The current (adapted) ``R`` ``(2, 2)`` m^2 of the pair."""
        return self._noise[(drone_id, target_id)].covariance.copy()

    @property
    def tracks(self) -> dict[int, Track]:
        """Current track of every target that has one, by target id."""
        out = {}
        for j in self.target_ids:
            ekf = self._filters.get(j)
            if ekf is None:
                continue
            accepted, rejected = self._last.get(j, (0, 0))
            out[j] = Track(
                j,
                self.t,
                ekf.mean.copy(),
                ekf.covariance.copy(),
                self.model.velocity(ekf.mean),
                accepted,
                rejected,
            )
        return out

    def update(self, t: float, measurements: Sequence[PositionMeasurement]) -> dict[int, Track]:
        """Predict every track to ``t`` (s, the time the predicted positions refer to; never
        before the previous update) and fuse ``measurements``; returns :attr:`tracks`.

        Raises ``ValueError`` for an unknown drone or target id or two measurements of one
        pair; non-finite positions are dropped and counted in :attr:`dropped`.
        """
        if not t >= self.t:
            raise ValueError(f"update time {t} s is before the last update at {self.t} s")
        by_target = self._group(measurements)
        for ekf in self._filters.values():
            ekf.predict(t - self.t)
        self.t = float(t)
        self._last = {}
        for j in self.target_ids:
            group = by_target.get(j, [])
            if j not in self._filters:
                if group:
                    self._birth(j, group)
                continue
            if group:
                self._fuse(j, group)
        return self.tracks

    def _group(
        self, measurements: Sequence[PositionMeasurement]
    ) -> dict[int, list[PositionMeasurement]]:
        seen: set[tuple[int, int]] = set()
        by_target: dict[int, list[PositionMeasurement]] = {}
        for m in measurements:
            pair = (m.drone_id, m.target_id)
            if pair not in self._noise:
                raise ValueError(
                    f"measurement from drone {m.drone_id} of target {m.target_id}: unknown id "
                    f"(drones {self.drone_ids}, targets {self.target_ids})"
                )
            if pair in seen:
                raise ValueError(
                    f"two measurements from drone {m.drone_id} of target "
                    f"{m.target_id} in one update"
                )
            seen.add(pair)
            position = np.asarray(m.position, dtype=float)
            if position.shape != (2,):
                raise ValueError(f"measurement position must have shape (2,), got {position.shape}")
            if not np.isfinite(position).all():
                self.dropped += 1
                continue
            by_target.setdefault(m.target_id, []).append(m)
        for group in by_target.values():
            group.sort(key=lambda m: m.drone_id)  # a fixed order makes runs reproducible
        return by_target

    def _birth(self, j: int, group: list[PositionMeasurement]) -> None:
        """Start (or restart) target ``j``'s track at the mean of ``group``'s positions; its
        covariance is that of the mean of independent measurements, ``(sum_i R_ij^-1)^-1``."""
        positions = np.array([m.position for m in group], dtype=float)
        info = sum(np.linalg.inv(self._noise[(m.drone_id, j)].covariance) for m in group)
        self._filters[j] = self._new_filter(positions.mean(axis=0), np.linalg.inv(info))
        self._misses[j] = 0
        self._last[j] = (len(group), 0)

    def _fuse(self, j: int, group: list[PositionMeasurement]) -> None:
        ekf = self._filters[j]
        accepted = 0
        for m in group:
            noise = self._noise[(m.drone_id, j)]
            diagnostics = ekf.update(np.asarray(m.position, dtype=float), noise.covariance)
            if diagnostics.accepted:
                accepted += 1
                if self.config.adaptive:
                    noise.observe(diagnostics)
        rejected = len(group) - accepted
        self.rejections += rejected
        self._last[j] = (accepted, rejected)
        self._misses[j] = self._misses[j] + 1 if accepted == 0 else 0
        if self.config.reset_after is not None and self._misses[j] >= self.config.reset_after:
            self.resets += 1
            self._birth(j, group)
            self._last[j] = (0, rejected)

    def forecast(self, dt: float) -> TrackForecast:
        """The planner's view (:class:`TrackForecast`) of the tracked targets, with the
        covariance propagated ``dt`` s (one planning step) ahead of the current tracks."""
        if not dt > 0:
            raise ValueError(f"forecast needs dt > 0 s, got {dt}")
        ids = tuple(j for j in self.target_ids if j in self._filters)
        n = self.model.ndim
        positions = np.zeros((len(ids), 2))
        predicted = np.zeros((len(ids), n, n))
        for k, j in enumerate(ids):
            ekf = self._filters[j]
            f = self.model.jacobian(ekf.mean, dt)
            positions[k] = ekf.mean[:2]
            predicted[k] = f @ ekf.covariance @ f.T + self.model.process_noise(ekf.mean, dt)
        noise = np.array(
            [[self._noise[(i, j)].covariance for j in ids] for i in self.drone_ids]
        ).reshape(len(self.drone_ids), len(ids), 2, 2)
        return TrackForecast(ids, self.drone_ids, positions, predicted, noise)
