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

from dronefl.tracking.adaptive import AdaptiveMeasurementNoise, floor_eigenvalues
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


def _inv2(m: np.ndarray) -> np.ndarray:
    """Closed-form inverse of a stack of ``(..., 2, 2)`` matrices."""
    det = m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] * m[..., 1, 0]
    inv = np.empty_like(m)
    inv[..., 0, 0] = m[..., 1, 1]
    inv[..., 1, 1] = m[..., 0, 0]
    inv[..., 0, 1] = -m[..., 0, 1]
    inv[..., 1, 0] = -m[..., 1, 0]
    return inv / det[..., None, None]


class RobustAdaptive(FusionMethod):
    r"""Adaptive-innovation EKF with Mahalanobis gating that survives real predictions.

    For target ``j`` with prior ``x^-, P^-`` (``A = H P^- H^T``) and the step's measurements
    ``z_i`` of its drones, every innovation is taken against the same prior, so the order of
    the drones does not matter (the first drone cannot capture the track):

    .. math::
        y_i = z_i - H x^-,\quad S_i = A + \tilde R_i,\quad d_i^2 = y_i^T S_i^{-1} y_i,\quad
        w_i = \min(1, k / d_i),\ \text{and } w_i = 0 \text{ if } d_i^2 > g

    with ``\tilde R_i = \rho_i R_i`` the pair's noise inflated by its effective-sample-size
    factor (below). The joint update with noises ``\tilde R_i / w_i`` is one update with the
    information-weighted measurement

    .. math::
        \Lambda = \sum_i w_i \tilde R_i^{-1},\quad \bar R = \Lambda^{-1},\quad
        \bar y = \bar R \sum_i w_i \tilde R_i^{-1} y_i,\quad
        K = P^- H^T (A + \bar R)^{-1},\quad x^+ = x^- + K \bar y

    and the Joseph-form covariance. Each accepted pair adapts its ``R`` from its weighted
    innovation, ``R_i \leftarrow \lfloor (1-\beta) R_i + \beta (w_i y_i y_i^T / c - A)
    \rfloor``, where ``c`` (:func:`huber_second_moment`) makes the sample unbiased for a
    consistent filter, so outliers neither move the track much nor blow up ``R``.

    Correlated errors: a drone's errors persist over many steps (lag-5 autocorrelation
    0.2-0.6), so ``n`` of its measurements carry the information of only about
    ``n (1 - \phi) / (1 + \phi)`` independent ones (``\phi`` the lag-1 autocorrelation of an
    AR(1) error). Each pair tracks ``\phi_i`` as an EMA of the product of consecutive whitened
    innovations, and the update uses ``\tilde R_i = R_i (1 + \phi_i) / (1 - \phi_i)``
    (``\phi_i`` clipped to ``[0, \phi_{max}]``) with ``config.decorrelate``.
    """

    def __init__(self, config: FusionConfig, n_drones: int, n_targets: int) -> None:
        super().__init__(config, n_drones, n_targets)
        self._r = np.broadcast_to(
            config.initial_noise_std**2 * np.eye(2), (n_drones, n_targets, 2, 2)
        ).copy()
        self._floor = config.noise_floor_std**2
        self._c = huber_second_moment(config.huber_threshold, config.gate)
        self._white = np.full((n_drones, n_targets, 2), np.nan)  # last whitened innovation
        self._energy = np.ones((n_drones, n_targets))  # EMA of the squared whitened innovation
        self._lag = np.zeros((n_drones, n_targets))  # EMA of its lag-1 product
        self._phi = np.zeros((n_drones, n_targets))  # lag-1 autocorrelation, lag / energy

    def noise(self) -> np.ndarray:
        return self._inflated(np.arange(self.n_drones)[:, None], np.arange(self.n_targets))

    def _inflated(self, drones: np.ndarray, target: np.ndarray | int) -> np.ndarray:
        r = self._r[drones, target]
        if not self.config.decorrelate:
            return r.copy()
        phi = np.clip(self._phi[drones, target], 0.0, self.config.max_autocorrelation)
        return r * ((1.0 + phi) / (1.0 - phi))[..., None, None]

    def update(self, target, drones, mean, covariance, positions) -> TargetUpdate:
        config = self.config
        a = covariance[:2, :2]  # H P^- H^T
        r = self._inflated(drones, target)  # (m, 2, 2)
        y = positions - mean[:2]  # (m, 2)
        s_inv = _inv2(a + r)
        nis = np.einsum("mi,mij,mj->m", y, s_inv, y)
        weight = huber_weight(nis, config.huber_threshold)
        accepted = np.ones(len(drones), dtype=bool) if config.gate is None else nis <= config.gate
        weight = np.where(accepted, weight, 0.0)
        if accepted.any():
            info = weight[:, None, None] * _inv2(r)  # w_i R_i^-1, (m, 2, 2)
            r_bar = _inv2(info.sum(axis=0))
            y_bar = r_bar @ np.einsum("mij,mj->i", info, y)
            s_bar_inv = _inv2(a + r_bar)
            k = covariance[:, :2] @ s_bar_inv  # (n, 2)
            i_kh = np.eye(len(mean))
            i_kh[:, :2] -= k
            mean = mean + k @ y_bar
            covariance = i_kh @ covariance @ i_kh.T + k @ r_bar @ k.T
        if config.adaptive:
            self._adapt(target, drones, y, a, s_inv, weight, accepted)
        return TargetUpdate(mean, covariance, accepted)

    def _adapt(self, target, drones, y, a, s_inv, weight, accepted) -> None:
        beta = self.config.adaptation_rate
        for k in np.flatnonzero(accepted):
            i = drones[k]
            sample = weight[k] * np.outer(y[k], y[k]) / self._c - a
            blended = (1.0 - beta) * self._r[i, target] + beta * sample
            self._r[i, target] = floor_eigenvalues(blended, self._floor)
        if not self.config.decorrelate:
            return
        # Whitened innovations (per axis, by the diagonal of S) and their products with the
        # pair's previous ones: the ratio of the two EMAs estimates the lag-1 autocorrelation.
        scale = np.sqrt(np.diagonal(s_inv, axis1=1, axis2=2))  # (m, 2)
        white = np.clip(y * scale, -3.0, 3.0)
        rate = self.config.autocorrelation_rate
        previous = self._white[drones, target]
        seen = np.isfinite(previous).all(axis=1)
        energy = (white**2).mean(axis=1)
        product = np.where(seen, (white * np.nan_to_num(previous)).mean(axis=1), 0.0)
        self._energy[drones, target] += rate * (energy - self._energy[drones, target])
        lag = self._lag[drones, target]
        self._lag[drones, target] = np.where(seen, lag + rate * (product - lag), lag)
        self._phi[drones, target] = self._lag[drones, target] / self._energy[drones, target]
        self._white[drones, target] = white


#: Fusion methods by name (``FusionConfig.method``).
FUSION_METHODS: dict[str, type[FusionMethod]] = {
    "paper": SequentialAdaptive,
    "robust": RobustAdaptive,
}
