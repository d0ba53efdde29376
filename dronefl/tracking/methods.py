"""Fusion methods: how one step's measurements of a target update its track and the noise ``R``
of each (drone, target) pair. One class per method, registered in :data:`FUSION_METHODS`; the
:class:`~dronefl.tracking.fusion.Fuser` picks one by :attr:`FusionConfig.method`.

* ``paper`` (:class:`SequentialAdaptive`): the paper's adaptive-innovation EKF: the drones'
  measurements one after another in drone-id order, each gated at ``gate`` and followed by the
  EMA adaptation of its pair's ``R``.
* ``robust`` (:class:`RobustAdaptive`): the same EKF and innovation-based ``R``, made to survive
  real predictions (biased, heavy-tailed, autocorrelated): every innovation is taken against the
  common prior (no drone goes first), down-weighted by a Huber weight instead of being accepted
  or rejected outright, ``R`` adapted from the weighted innovations, and inflated by each pair's
  effective-sample-size factor when its innovations are autocorrelated.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.special import gammainc

from dronefl.tracking.adaptive import AdaptiveMeasurementNoise
from dronefl.tracking.ekf import position_update

if TYPE_CHECKING:
    from dronefl.tracking.fusion import FusionConfig


@dataclass(frozen=True)
class TargetUpdate:
    """A target's posterior ``mean`` ``(n,)`` / ``covariance`` ``(n, n)`` after one step's
    measurements, and which of them were fused (``accepted`` ``(m,)``; the others were gated
    out)."""

    mean: np.ndarray
    covariance: np.ndarray
    accepted: np.ndarray


class FusionMethod(ABC):
    """Updates targets from their measurements and owns every pair's noise ``R`` (m^2).

    ``config``: the :class:`FusionConfig`; ``n_drones`` / ``n_targets``: the sizes of the
    index space (drones and targets are addressed by their index in the Fuser's id tuples).
    """

    def __init__(self, config: FusionConfig, n_drones: int, n_targets: int) -> None:
        self.config = config
        self.n_drones = n_drones
        self.n_targets = n_targets

    @abstractmethod
    def noise(self) -> np.ndarray:
        """Every pair's current ``R`` ``(n_drones, n_targets, 2, 2)``, m^2 (a copy)."""

    @abstractmethod
    def update(
        self,
        target: int,
        drones: np.ndarray,
        mean: np.ndarray,
        covariance: np.ndarray,
        positions: np.ndarray,
    ) -> TargetUpdate:
        """Fuse the positions ``(m, 2)`` m that drones ``drones`` ``(m,)`` (indices, ascending)
        report of target ``target`` into its prior ``mean`` ``(n,)`` / ``covariance``
        ``(n, n)``, adapting those pairs' ``R``."""


class SequentialAdaptive(FusionMethod):
    r"""The paper's fusion (SPEC §6): sequential gated EKF updates in drone order,

    .. math::
        d^2_{ij} = y_{ij}^T S_{ij}^{-1} y_{ij} \le g \Rightarrow
        x_j \leftarrow x_j + K y_{ij},\quad
        R_{ij} \leftarrow \text{EMA}(y_{ij} y_{ij}^T - H P_j^- H^T)

    each innovation taken against the estimate the earlier drones left
    (:class:`~dronefl.tracking.adaptive.AdaptiveMeasurementNoise`).
    """

    def __init__(self, config: FusionConfig, n_drones: int, n_targets: int) -> None:
        super().__init__(config, n_drones, n_targets)
        r0 = config.initial_noise_std**2 * np.eye(2)
        self._noise = [
            [
                AdaptiveMeasurementNoise(
                    r0, config.adaptation_rate, config.noise_floor_std**2, config.gate
                )
                for _ in range(n_targets)
            ]
            for _ in range(n_drones)
        ]

    def noise(self) -> np.ndarray:
        return np.array([[n.covariance for n in row] for row in self._noise])

    def update(self, target, drones, mean, covariance, positions) -> TargetUpdate:
        accepted = np.zeros(len(drones), dtype=bool)
        for k, i in enumerate(drones):
            noise = self._noise[i][target]
            mean, covariance, diagnostics = position_update(
                mean, covariance, positions[k], noise.covariance, self.config.gate
            )
            accepted[k] = diagnostics.accepted
            if diagnostics.accepted and self.config.adaptive:
                noise.observe(diagnostics)
        return TargetUpdate(mean, covariance, accepted)


def huber_weight(nis: np.ndarray, threshold: float) -> np.ndarray:
    r"""Huber weights ``w(d) = min(1, k / d)`` of Mahalanobis distances ``d = sqrt(nis)`` with
    ``k^2 = threshold``: an innovation is used at full weight up to ``k`` and with its noise
    inflated by ``d / k`` beyond (Huber 1964; the M-estimation form of a robust Kalman update,
    e.g. Karlgaard & Schaub 2007)."""
    return np.minimum(1.0, np.sqrt(threshold / np.maximum(nis, 1e-300)))


def huber_second_moment(threshold: float, gate: float | None) -> float:
    r"""``E[w(d) w_1^2 | d^2 <= g]`` for ``w ~ N(0, I_2)``, ``d^2 = |w|^2``: the factor by which
    Huber weighting at ``k^2 = threshold`` and gating at ``g`` shrink the weighted second moment
    of a consistent filter's whitened innovation per axis. With ``u = d^2 ~ Exp(1/2)``:

    .. math::
        E[w u\,1_{u \le g}] = 2 P(2, \tfrac{k^2}{2}) + k \sqrt{2}\,\Gamma(\tfrac32)
        \left(P(\tfrac32, \tfrac g2) - P(\tfrac32, \tfrac{k^2}{2})\right)

    (``P`` the regularised lower incomplete gamma function), divided by ``2 P(1, g/2)``.
    """
    g = math.inf if gate is None else gate
    k2 = min(threshold, g)
    core = 2.0 * gammainc(2.0, k2 / 2.0)
    tail = 0.0
    if g > k2:
        upper = 1.0 if math.isinf(g) else gammainc(1.5, g / 2.0)
        tail = math.sqrt(k2) * math.sqrt(2.0) * math.gamma(1.5) * (upper - gammainc(1.5, k2 / 2.0))
    accepted = 1.0 if math.isinf(g) else gammainc(1.0, g / 2.0)
    return (core + tail) / (2.0 * accepted)


class RobustAdaptive(FusionMethod):
    r"""Adaptive-innovation EKF with Mahalanobis gating that survives real predictions.

    For target ``j`` with prior ``x^-, P^-`` (``A = H P^- H^T``) and the step's measurements
    ``z_i`` of its drones, every innovation is taken against the same prior, so the order of
    the drones does not matter (the first drone cannot capture the track).

    *Correlated errors.* A drone's prediction errors persist over many steps (lag-1
    autocorrelation ``phi`` ~0.85 at 5 Hz), so ``n`` of its measurements carry the information
    of only ``n (1 - phi) / (1 + phi)`` independent ones. Every update therefore uses
    ``	ilde R_i = R_i (1 + phi) / (1 - phi)`` (``error_autocorrelation``), which keeps ``P``
    honest instead of shrinking it as if the errors were white.

    *Outliers, not lagging tracks.* With two or more drones, a measurement is judged against
    the others, not against the prior: its leave-one-out residual
    ``r_i = z_i - ar z_{-i}`` (``ar z_{-i}`` the information-weighted mean of the other
    drones' positions, covariance ``ar R_{-i}``) gives ``d_i^2 = r_i^T (	ilde R_i +
    ar R_{-i})^{-1} r_i``. Beyond ``k^2 = huber_threshold`` the measurement's weight falls as
    ``w_i = k / d_i`` (Huber); beyond the gate it is rejected (of two drones that disagree, the
    one farther from the prior). A lone measurement is judged by its innovation
    ``y_i^T (A + 	ilde R_i)^{-1} y_i`` as in the paper. If the weighted consensus itself lies
    outside the gate of the prior, the track is lagging: ``P^-`` is inflated by
    ``\lambda = d^2 / g`` (a fading factor) so the update follows the drones instead of the
    gate rejecting all of them.

    *Update.* The joint update with noises ``	ilde R_i / w_i`` is one update with

    .. math::
        \Lambda = \sum_i w_i 	ilde R_i^{-1},\quad ar R = \Lambda^{-1},\quad
        ar y = ar R \sum_i w_i 	ilde R_i^{-1} y_i,\quad
        K = P^- H^T (A + ar R)^{-1},\quad x^+ = x^- + K ar y

    and the Joseph-form covariance.

    *Adaptive R.* With ``noise_estimate = "consensus"`` and two or more drones, ``R_i`` is the
    EMA of ``w_i r_i r_i^T / c - ar R_{-i}`` (the leave-one-out residual measures the drone's
    whole error, slow parts included, which the innovation against a prior that has followed
    the same slow error does not); otherwise, of ``w_i y_i y_i^T / c - A`` (the paper's
    innovation form). ``c`` (:func:`huber_second_moment`) makes the sample unbiased for
    Gaussian errors; the eigenvalue floor keeps ``R`` positive definite.
    """

    def __init__(self, config: FusionConfig, n_drones: int, n_targets: int) -> None:
        super().__init__(config, n_drones, n_targets)
        r0 = config.initial_noise_std**2
        # R_ij as (xx, xy, yy) floats: the 2 x 2 algebra below runs on Python floats, which
        # costs a fraction of numpy's per-call overhead at this size.
        self._r = [[(r0, 0.0, r0) for _ in range(n_targets)] for _ in range(n_drones)]
        self._floor = config.noise_floor_std**2
        self._c = huber_second_moment(config.huber_threshold, config.gate)
        self._c_consensus = huber_second_moment(config.huber_threshold, config.consensus_gate)
        phi = config.error_autocorrelation
        self._inflation = (1.0 + phi) / (1.0 - phi)

    def noise(self) -> np.ndarray:
        out = np.empty((self.n_drones, self.n_targets, 2, 2))
        for i, row in enumerate(self._r):
            for j, (xx, xy, yy) in enumerate(row):
                out[i, j] = ((xx, xy), (xy, yy))
        return out * self._inflation

    def update(self, target, drones, mean, covariance, positions) -> TargetUpdate:
        config = self.config
        gate = math.inf if config.gate is None else config.gate
        k2 = config.huber_threshold
        inflation = self._inflation
        m = len(drones)
        ax, axy, ay = covariance[0, 0], covariance[0, 1], covariance[1, 1]  # A = H P^- H^T
        px, py = mean[0], mean[1]
        z = positions.tolist()
        r = [tuple(v * inflation for v in self._r[i][target]) for i in drones.tolist()]
        info = [_inv_sym(*ri) for ri in r]  # R_i^-1
        y = [(zi[0] - px, zi[1] - py) for zi in z]
        prior_nis = [
            _quad(yi, _inv_sym(ax + ri[0], axy + ri[1], ay + ri[2]))
            for yi, ri in zip(y, r, strict=True)
        ]
        residual = rest = None
        if m >= 2 and config.consensus_gate is not None:
            accepted, nis, residual, rest = _consensus_gate(
                z, r, info, prior_nis, config.consensus_gate, gate
            )
        else:
            nis = prior_nis
            accepted = [d <= gate for d in nis]
        weight = [
            (1.0 if d <= k2 else math.sqrt(k2 / d)) if ok else 0.0
            for d, ok in zip(nis, accepted, strict=True)
        ]
        if any(accepted):
            lx = lxy = ly = bx = by = 0.0  # Lambda = sum w R^-1, b = sum w R^-1 y
            for w, (ix, ixy, iy), (yx, yy) in zip(weight, info, y, strict=True):
                lx, lxy, ly = lx + w * ix, lxy + w * ixy, ly + w * iy
                bx, by = bx + w * (ix * yx + ixy * yy), by + w * (ixy * yx + iy * yy)
            rbx, rbxy, rby = _inv_sym(lx, lxy, ly)  # R_bar
            ybar = (rbx * bx + rbxy * by, rbxy * bx + rby * by)
            s_inv = _inv_sym(ax + rbx, axy + rbxy, ay + rby)
            fused_nis = _quad(ybar, s_inv)
            if config.fading and fused_nis > gate:  # a lagging track: trust the drones
                covariance = covariance * min(fused_nis / gate, MAX_FADING)
                ax, axy, ay = covariance[0, 0], covariance[0, 1], covariance[1, 1]
                s_inv = _inv_sym(ax + rbx, axy + rbxy, ay + rby)
            k = covariance[:, :2] @ np.array(((s_inv[0], s_inv[1]), (s_inv[1], s_inv[2])))
            i_kh = np.eye(len(mean))
            i_kh[:, :2] -= k
            r_bar = np.array(((rbx, rbxy), (rbxy, rby)))
            mean = mean + k @ ybar
            covariance = i_kh @ covariance @ i_kh.T + k @ r_bar @ k.T
        if config.adaptive:
            self._adapt(target, drones, y, (ax, axy, ay), residual, rest, weight, accepted)
        return TargetUpdate(mean, covariance, np.array(accepted, dtype=bool))

    def _adapt(self, target, drones, y, a, residual, rest, weight, accepted) -> None:
        beta = self.config.adaptation_rate
        used = [row for row, ok in enumerate(accepted) if ok]
        estimate = self.config.noise_estimate
        if residual is None or len(used) < 2:
            estimate = "innovation"
        c = self._c if estimate == "innovation" else self._c_consensus
        scale = 1.0 / (c * self._inflation)  # R_i is kept without the inflation
        zero = (0.0, 0.0, 0.0)
        for row in used:
            i = int(drones[row])
            w = weight[row] * scale
            yx, yy = y[row]
            if estimate == "innovation":  # y y^T - A
                base, u, v = a, (yx, yy), (yx, yy)
            elif estimate == "consensus":  # r r^T - R_-i
                base, u, v = rest[row], residual[row], residual[row]
            else:  # the prior as the third corner: sym(y r^T)
                base, u, v = zero, (yx, yy), residual[row]
            sample = (u[0] * v[0], 0.5 * (u[0] * v[1] + u[1] * v[0]), u[1] * v[1])
            sample = tuple(w * s - b / self._inflation for s, b in zip(sample, base, strict=True))
            old = self._r[i][target]
            self._r[i][target] = _floor_sym(
                *((1.0 - beta) * o + beta * s for o, s in zip(old, sample, strict=True)),
                self._floor,
            )


def _inv_sym(xx: float, xy: float, yy: float) -> tuple[float, float, float]:
    """Inverse of the symmetric ``[[xx, xy], [xy, yy]]`` as ``(xx, xy, yy)``."""
    det = xx * yy - xy * xy
    return yy / det, -xy / det, xx / det


def _quad(v: tuple[float, float], m: tuple[float, float, float]) -> float:
    """``v^T M v`` for a symmetric ``M = (xx, xy, yy)``."""
    return m[0] * v[0] * v[0] + 2.0 * m[1] * v[0] * v[1] + m[2] * v[1] * v[1]


def _floor_sym(xx: float, xy: float, yy: float, floor: float) -> tuple[float, float, float]:
    """:func:`~dronefl.tracking.adaptive.floor_eigenvalues` of ``[[xx, xy], [xy, yy]]``, in
    closed form (the eigenvalues of a symmetric 2 x 2 are ``mid -+ sqrt(half^2 + xy^2)``)."""
    mid, half = 0.5 * (xx + yy), 0.5 * (xx - yy)
    radius = math.hypot(half, xy)
    low, high = mid - radius, mid + radius
    if low >= floor:
        return xx, xy, yy
    if radius == 0.0:
        return floor, 0.0, floor
    # eigenvector of the larger eigenvalue: (cos t, sin t) with tan 2t = 2 xy / (xx - yy)
    c2, s2 = half / radius, xy / radius  # cos 2t, sin 2t
    high, low = max(high, floor), floor
    mid, half = 0.5 * (high + low), 0.5 * (high - low)
    return mid + half * c2, half * s2, mid - half * c2


def _consensus_gate(z, r, info, prior_nis, gate, prior_gate):
    """Gate measurements against each other: while some leave-one-out residual's ``d^2``
    exceeds ``gate``, reject the worst and recompute among the rest (a single wild drone must not
    drag the others' residuals out of the gate); a last survivor is judged against the prior
    (``prior_gate``).
    Returns ``(accepted, d^2, residuals, residual covariances)`` per measurement (residuals and
    their covariances from the final set; rejected ones keep their last values)."""
    m = len(z)
    alive = list(range(m))
    accepted, nis = [False] * m, list(prior_nis)
    residual, rest = [(0.0, 0.0)] * m, [(0.0, 0.0, 0.0)] * m
    while len(alive) >= 2:
        res, cov = _leave_one_out([z[k] for k in alive], [info[k] for k in alive])
        d2 = []
        for k, e, c in zip(alive, res, cov, strict=True):
            rk = r[k]
            residual[k], rest[k] = e, c
            d2.append(_quad(e, _inv_sym(rk[0] + c[0], rk[1] + c[1], rk[2] + c[2])))
        worst = max(range(len(alive)), key=d2.__getitem__)
        if d2[worst] <= gate:
            for k, d in zip(alive, d2, strict=True):
                accepted[k], nis[k] = True, d
            return accepted, nis, residual, rest
        if len(alive) == 2:  # two that disagree: keep the one nearer the prior
            worst = max((0, 1), key=lambda a: prior_nis[alive[a]])
        nis[alive[worst]] = d2[worst]
        alive.pop(worst)
    last = alive[0]
    accepted[last] = prior_nis[last] <= prior_gate
    return accepted, nis, None if sum(accepted) < 2 else residual, rest


def _leave_one_out(
    z: list, info: list[tuple[float, float, float]]
) -> tuple[list[tuple[float, float]], list[tuple[float, float, float]]]:
    """Each measurement's residual from the information-weighted mean of the others,
    ``r_i = z_i - \bar z_{-i}`` (m), and that mean's covariance ``\bar R_{-i}`` (m^2),
    from positions ``z`` ``[(x, y), ...]`` and information matrices ``R_i^-1`` (``m >= 2``)."""
    tx = sum(v[0] for v in info)
    txy = sum(v[1] for v in info)
    ty = sum(v[2] for v in info)
    wz = [
        (v[0] * p[0] + v[1] * p[1], v[1] * p[0] + v[2] * p[1]) for v, p in zip(info, z, strict=True)
    ]
    sx, sy = sum(w[0] for w in wz), sum(w[1] for w in wz)
    residuals, rests = [], []
    for v, w, p in zip(info, wz, z, strict=True):
        rx, rxy, ry = _inv_sym(tx - v[0], txy - v[1], ty - v[2])
        cx, cy = sx - w[0], sy - w[1]
        residuals.append((p[0] - (rx * cx + rxy * cy), p[1] - (rxy * cx + ry * cy)))
        rests.append((rx, rxy, ry))
    return residuals, rests


#: Largest fading factor applied to a lagging track's prior covariance in one update.
MAX_FADING = 2.0

#: Fusion methods by name (``FusionConfig.method``).
FUSION_METHODS: dict[str, type[FusionMethod]] = {
    "paper": SequentialAdaptive,
    "robust": RobustAdaptive,
}
