"""One extended Kalman filter per target, with gating and per-update diagnostics (SPEC §6)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dronefl.tracking.models import MotionModel

#: chi-square quantile for 2 degrees of freedom at 99 %: ``-2 ln(0.01)`` = 9.2103.
CHI2_2DOF_99 = -2.0 * math.log(0.01)
#: chi-square quantile for 2 degrees of freedom at 99.9 %: ``-2 ln(0.001)`` = 13.8155.
CHI2_2DOF_999 = -2.0 * math.log(0.001)


@dataclass(frozen=True)
class UpdateDiagnostics:
    """What one measurement update saw (filterpy keeps the same after each ``update``).

    ``innovation`` ``y = z - H x^-`` ``(2,)`` m; ``innovation_covariance``
    ``S = H P^- H^T + R`` ``(2, 2)`` m^2; ``predicted_covariance`` ``H P^- H^T`` ``(2, 2)`` m^2
    (the state's share of ``S``); ``gain`` ``K`` ``(n, 2)`` (zeros when rejected);
    ``nis`` the normalised innovation squared ``d^2 = y^T S^-1 y`` (the squared Mahalanobis
    distance, chi-square with 2 dof for a consistent filter); ``accepted`` whether ``d^2`` passed
    the gate and the state was updated.
    """

    innovation: np.ndarray
    innovation_covariance: np.ndarray
    predicted_covariance: np.ndarray
    gain: np.ndarray
    nis: float
    accepted: bool


class ExtendedKalmanFilter:
    r"""EKF on a :class:`MotionModel` with linear position measurements ``z = H x + v``.

    Predict (``F`` the model Jacobian at the prior mean):

    .. math::
        x^- = f(x, \Delta t),\qquad P^- = F P F^T + Q

    Update with a position ``z`` of noise covariance ``R``:

    .. math::
        y = z - H x^-,\quad S = H P^- H^T + R,\quad K = P^- H^T S^{-1},\quad
        d^2 = y^T S^{-1} y

        x^+ = x^- + K y,\qquad P^+ = (I - K H) P^- (I - K H)^T + K R K^T

    The covariance update is the Joseph form: it stays symmetric positive semi-definite under
    rounding and for any gain, which the short form ``(I - K H) P^-`` does not guarantee when
    many updates shrink ``P`` (Bar-Shalom et al. 2001, §5.2.3). ``S`` is ``2 x 2`` and at least
    ``R`` (whose eigenvalues the fusion keeps above a floor), so its closed-form inverse is well
    conditioned and several times cheaper than a general solve.

    Gating: with ``gate`` set, an update whose ``d^2`` exceeds it is rejected (state unchanged)
    and counted in :attr:`rejections`; :data:`CHI2_2DOF_99` (9.21) rejects 1 % of consistent
    measurements. After every update :attr:`diagnostics` holds its :class:`UpdateDiagnostics`.

    ``mean`` ``(n,)`` and ``covariance`` ``(n, n)`` are the current state estimate.
    """

    def __init__(
        self,
        model: MotionModel,
        mean: np.ndarray,
        covariance: np.ndarray,
        gate: float | None = CHI2_2DOF_99,
    ) -> None:
        n = model.ndim
        mean = np.asarray(mean, dtype=float)
        covariance = np.asarray(covariance, dtype=float)
        if mean.shape != (n,):
            raise ValueError(f"mean must have shape ({n},), got {mean.shape}")
        if covariance.shape != (n, n):
            raise ValueError(f"covariance must have shape ({n}, {n}), got {covariance.shape}")
        if not (np.isfinite(mean).all() and np.isfinite(covariance).all()):
            raise ValueError("mean and covariance must be finite")
        if gate is not None and not gate > 0:
            raise ValueError(f"gate must be a positive squared Mahalanobis distance, got {gate}")
        self.model = model
        self.mean = mean.copy()
        self.covariance = covariance.copy()
        self.gate = gate
        self.rejections = 0
        self.diagnostics: UpdateDiagnostics | None = None

    def predict(self, dt: float) -> None:
        """Propagate the estimate ``dt`` s ahead (``dt >= 0``; 0 leaves it unchanged)."""
        if not dt >= 0:
            raise ValueError(f"predict needs dt >= 0 s, got {dt}")
        if dt == 0:
            return
        f = self.model.jacobian(self.mean, dt)
        q = self.model.process_noise(self.mean, dt)
        self.mean = self.model.transition(self.mean, dt)
        self.covariance = f @ self.covariance @ f.T + q

    def update(self, z: np.ndarray, r: np.ndarray) -> UpdateDiagnostics:
        """Fuse one position measurement ``z`` ``(2,)`` m with noise covariance ``r`` ``(2, 2)``
        m^2; returns (and keeps in :attr:`diagnostics`) what the update saw."""
        z = np.asarray(z, dtype=float)
        r = np.asarray(r, dtype=float)
        if z.shape != (2,) or r.shape != (2, 2):
            raise ValueError(f"need z (2,) and R (2, 2), got {z.shape} and {r.shape}")
        self.mean, self.covariance, self.diagnostics = position_update(
            self.mean, self.covariance, z, r, self.gate
        )
        if not self.diagnostics.accepted:
            self.rejections += 1
        return self.diagnostics


def position_update(
    mean: np.ndarray, covariance: np.ndarray, z: np.ndarray, r: np.ndarray, gate: float | None
) -> tuple[np.ndarray, np.ndarray, UpdateDiagnostics]:
    """The gated Kalman update of ``(mean (n,), covariance (n, n))`` with a position ``z``
    ``(2,)`` m of noise ``r`` ``(2, 2)`` m^2 (equations in :class:`ExtendedKalmanFilter`);
    returns the new mean, covariance and the update's diagnostics (a rejected update returns
    the inputs unchanged). ``H = [I_2 0]``, so ``H P`` is the first two rows of ``P``."""
    n = len(mean)
    hp = covariance[:2]  # H P, (2, n)
    hph = hp[:, :2]
    s = hph + r
    s_inv = _inv2(s)
    y = z - mean[:2]
    nis = float(y @ s_inv @ y)
    if gate is not None and nis > gate:
        return mean, covariance, UpdateDiagnostics(y, s, hph, np.zeros((n, 2)), nis, False)
    k = hp.T @ s_inv  # K = P H^T S^-1, (n, 2)
    i_kh = np.eye(n)
    i_kh[:, :2] -= k
    new_mean = mean + k @ y
    new_covariance = i_kh @ covariance @ i_kh.T + k @ r @ k.T
    return new_mean, new_covariance, UpdateDiagnostics(y, s, hph, k, nis, True)


def _inv2(m: np.ndarray) -> np.ndarray:
    """Closed-form inverse of a ``(2, 2)`` matrix."""
    det = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    if not (det > 0 and m[0, 0] > 0):
        raise ValueError(f"innovation covariance S is not positive definite: {m.tolist()}")
    return np.array([[m[1, 1], -m[0, 1]], [-m[1, 0], m[0, 0]]]) / det


def inv2_stack(m: np.ndarray) -> np.ndarray:
    """Closed-form inverse of a stack of ``(..., 2, 2)`` matrices."""
    det = m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] * m[..., 1, 0]
    inv = np.empty_like(m)
    inv[..., 0, 0] = m[..., 1, 1]
    inv[..., 1, 1] = m[..., 0, 0]
    inv[..., 0, 1] = -m[..., 0, 1]
    inv[..., 1, 0] = -m[..., 1, 0]
    return inv / det[..., None, None]
