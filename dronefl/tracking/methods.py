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
    from dronefl.tracking.config import FusionConfig


@dataclass(frozen=True)
class MeasurementBatch:
    """One update's measurements of tracked targets, the rows sorted by target, then drone.

    ``target`` / ``drone`` ``(K,)``: indices into the Fuser's id tuples (each pair at most
    once); ``position`` ``(K, 2)`` m. ``targets`` ``(G,)``: the distinct targets, ascending;
    ``start`` / ``count`` ``(G,)``: the first row and the number of rows of each; ``group``
    ``(K,)``: each row's place in ``targets``. ``reported`` ``(K, 3)``: each drone's reported
    noise as ``(xx, xy, yy)`` m² (NaN where it sent none).
    """

    target: np.ndarray
    drone: np.ndarray
    position: np.ndarray
    targets: np.ndarray
    start: np.ndarray
    count: np.ndarray
    group: np.ndarray
    reported: np.ndarray

    @classmethod
    def of(
        cls,
        target: np.ndarray,
        drone: np.ndarray,
        position: np.ndarray,
        reported: np.ndarray | None = None,
    ) -> MeasurementBatch:
        """The rows ``target`` / ``drone`` ``(K,)``, ``position`` ``(K, 2)`` m and ``reported``
        ``(K, 3)`` m² (default: none), sorted and grouped."""
        if reported is None:
            reported = np.full((len(target), 3), np.nan)
        order = np.lexsort((drone, target))
        target, drone = target[order], drone[order]
        position, reported = position[order], reported[order]
        per_target = np.bincount(target)  # rows of every target index
        targets = per_target.nonzero()[0]
        count = per_target[targets]
        group = (per_target > 0).cumsum()[target] - 1
        start = count.cumsum() - count
        return cls(target, drone, position, targets, start, count, group, reported)

    def rows(self, group: int) -> slice:
        """The rows of ``targets[group]``."""
        start = int(self.start[group])
        return slice(start, start + int(self.count[group]))

    def select(self, keep: np.ndarray) -> MeasurementBatch:
        """The batch of the targets where ``keep`` ``(G,)`` is set."""
        rows = keep[self.group]
        return MeasurementBatch.of(
            self.target[rows],
            self.drone[rows],
            self.position[rows],
            self.reported[rows],
        )


@dataclass(frozen=True)
class BatchUpdate:
    """The posteriors ``mean`` ``(G, n)`` / ``covariance`` ``(G, n, n)`` of a batch's targets
    after their measurements, and which measurements were fused (``accepted`` ``(K,)``; the
    others were gated out)."""

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
        self, batch: MeasurementBatch, mean: np.ndarray, covariance: np.ndarray
    ) -> BatchUpdate:
        """Fuse ``batch`` (one update's measurements) into the priors ``mean`` ``(G, n)`` /
        ``covariance`` ``(G, n, n)`` of ``batch.targets``, adapting the measured pairs' ``R``
        (the inputs are left unchanged)."""

    @abstractmethod
    def state(self) -> np.ndarray:
        """What the method adapts (every pair's noise, in its own form), for a checkpoint."""

    @abstractmethod
    def restore(self, state: np.ndarray) -> None:
        """Continue from ``state`` (:meth:`state` of a method of the same sizes)."""


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

    def state(self) -> np.ndarray:
        return self.noise()

    def restore(self, state: np.ndarray) -> None:
        for row, covariances in zip(self._noise, state, strict=True):
            for noise, covariance in zip(row, covariances, strict=True):
                noise.covariance = covariance.copy()

    def update(self, batch, mean, covariance) -> BatchUpdate:
        mean, covariance = mean.copy(), covariance.copy()
        accepted = np.zeros(len(batch.target), dtype=bool)
        drones = batch.drone.tolist()
        for g, j in enumerate(batch.targets.tolist()):
            x, p = mean[g], covariance[g]
            rows = batch.rows(g)
            for k in range(rows.start, rows.stop):
                noise = self._noise[drones[k]][j]
                x, p, diagnostics = position_update(
                    x, p, batch.position[k], noise.covariance, self.config.gate
                )
                accepted[k] = diagnostics.accepted
                if diagnostics.accepted and self.config.adaptive:
                    noise.observe(diagnostics)
            mean[g], covariance[g] = x, p
        return BatchUpdate(mean, covariance, accepted)


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
    ``\tilde R_i = R_i (1 + phi) / (1 - phi)`` (``error_autocorrelation``), which keeps ``P``
    honest instead of shrinking it as if the errors were white.

    *Outliers, not lagging tracks.* With two or more drones, a measurement is judged against
    the others, not against the prior: its leave-one-out residual
    ``r_i = z_i - \bar z_{-i}`` (``\bar z_{-i}`` the information-weighted mean of the other
    drones' positions, covariance ``\bar R_{-i}``) gives ``d_i^2 = r_i^T (\tilde R_i +
    \bar R_{-i})^{-1} r_i``. Beyond ``k^2 = huber_threshold`` the measurement's weight falls as
    ``w_i = k / d_i`` (Huber); beyond the gate it is rejected (of two drones that disagree, the
    one farther from the prior). A lone measurement is judged by its innovation
    ``y_i^T (A + \tilde R_i)^{-1} y_i`` as in the paper. If the weighted consensus itself lies
    outside the gate of the prior, the track is lagging: ``P^-`` is inflated by
    ``\lambda = d^2 / g`` (a fading factor) so the update follows the drones instead of the
    gate rejecting all of them.

    *Update.* The joint update with noises ``\tilde R_i / w_i`` is one update with

    .. math::
        \Lambda = \sum_i w_i \tilde R_i^{-1},\quad \bar R = \Lambda^{-1},\quad
        \bar y = \bar R \sum_i w_i \tilde R_i^{-1} y_i,\quad
        K = P^- H^T (A + \bar R)^{-1},\quad x^+ = x^- + K \bar y

    and the Joseph-form covariance.

    *Adaptive R.* With ``noise_estimate = "consensus"`` and two or more drones, ``R_i`` is the
    EMA of ``w_i r_i r_i^T / c - \bar R_{-i}`` (the leave-one-out residual measures the drone's
    whole error, slow parts included, which the innovation against a prior that has followed
    the same slow error does not); otherwise, of ``w_i y_i y_i^T / c - A`` (the paper's
    innovation form). ``c`` (:func:`huber_second_moment`) makes the sample unbiased for
    Gaussian errors; the eigenvalue floor keeps ``R`` positive definite.

    *Reported split.* Two drones' residual measures ``R_1 + R_2``, never the split: the
    adaptation leaves it where the errors' slow parts push it. With ``noise_split =
    "reported"`` every step first shares the adapted total of a target's drones in proportion
    to the noises they report (:meth:`_split_by_reports`).
    """

    def __init__(self, config: FusionConfig, n_drones: int, n_targets: int) -> None:
        super().__init__(config, n_drones, n_targets)
        r0 = config.initial_noise_std**2
        # R_ij as its components (xx, xy, yy), (3, n_drones, n_targets): the 2 x 2 algebra
        # below runs on component arrays of all of a step's measurements at once, a few dozen
        # numpy calls per step instead of many small matrices per measurement.
        self._r = np.zeros((3, n_drones, n_targets))
        self._r[0] = self._r[2] = r0
        self._floor = config.noise_floor_std**2
        self._c = huber_second_moment(config.huber_threshold, config.gate)
        self._c_consensus = huber_second_moment(config.huber_threshold, config.consensus_gate)
        phi = config.error_autocorrelation
        self._inflation = (1.0 + phi) / (1.0 - phi)

    def noise(self) -> np.ndarray:
        return _matrix(self._r * self._inflation)

    def state(self) -> np.ndarray:
        return self._r.copy()

    def restore(self, state: np.ndarray) -> None:
        self._r = np.array(state, dtype=float)

    def update(self, batch, mean, covariance) -> BatchUpdate:
        config = self.config
        gate = math.inf if config.gate is None else config.gate
        if config.noise_split == "reported":
            self._split_by_reports(batch)
        group = batch.group
        z = batch.position.T  # (2, K)
        r = self._r[:, batch.drone, batch.target] * self._inflation  # R~_i
        info = _inv_sym(r)  # R~_i^-1
        y = z - mean[group, :2].T  # innovations against the common prior, (2, K)
        a = covariance[:, _XX_XY_YY[0], _XX_XY_YY[1]].T  # A = H P^- H^T, (3, G)
        prior_nis = _quad(y, _inv_sym(a[:, group] + r))
        if config.consensus_gate is None:
            accepted, nis = prior_nis <= gate, prior_nis
            residual, rest = np.zeros(y.shape), np.zeros(r.shape)
            consensus = np.zeros(len(batch.targets), dtype=bool)
        else:
            accepted, nis, residual, rest, consensus = _consensus_gate(
                batch, z, r, info, prior_nis, config.consensus_gate, gate
            )
        weight = np.where(accepted, huber_weight(nis, config.huber_threshold), 0.0)
        used = np.add.reduceat(accepted, batch.start, dtype=int)  # fused per target, (G,)
        mean, covariance = mean.copy(), covariance.copy()  # a target with none keeps its prior
        live = used.nonzero()[0]  # (G',)
        if live.size:
            lam = np.add.reduceat(weight * info, batch.start, axis=1)[:, live]
            b = np.add.reduceat(weight * _apply(info, y), batch.start, axis=1)[:, live]
            mean[live], covariance[live], a[:, live] = _joint_update(
                mean[live], covariance[live], a[:, live], lam, b, config.fading, gate
            )
        if config.adaptive:
            self._adapt(batch, y, a, residual, rest, weight, accepted, consensus)
        return BatchUpdate(mean, covariance, accepted)

    def _split_by_reports(self, batch: MeasurementBatch) -> None:
        r"""Share the adapted noise of every target that two or more drones see, all with a
        report, in proportion to their reported noises ``S_i``:
        ``R_i <- S_i \sum_k tr R_k / \sum_k tr S_k`` (the total trace is kept: the drones'
        consensus measures the sum, not the split)."""
        reported = batch.reported.T  # (3, K)
        has = np.isfinite(reported).all(axis=0) & (reported[0] + reported[2] > 0)
        complete = np.add.reduceat(has, batch.start, dtype=int) == batch.count  # (G,)
        rows = (complete & (batch.count >= 2))[batch.group]
        if not rows.any():
            return
        drone, target, group = batch.drone[rows], batch.target[rows], batch.group[rows]
        shares = reported[:, rows]
        current = self._r[:, drone, target]
        n = len(batch.targets)
        total = np.bincount(group, weights=current[0] + current[2], minlength=n)
        reported_total = np.bincount(group, weights=shares[0] + shares[2], minlength=n)
        scale = total[group] / reported_total[group]
        self._r[:, drone, target] = _floor_sym(shares * scale, self._floor)

    def _adapt(self, batch, y, a, residual, rest, weight, accepted, consensus) -> None:
        """EMA of every fused pair's ``R`` toward its weighted sample (class doc): from the
        leave-one-out residuals ``residual`` ``(2, K)`` / ``rest`` ``(3, K)`` for the targets
        where ``consensus`` ``(G,)`` is set, else from the innovations ``y`` ``(2, K)`` and
        ``A`` ``(3, G)``."""
        rows = accepted.nonzero()[0]
        if not rows.size:
            return
        beta, inflation = self.config.adaptation_rate, self._inflation
        estimate = self.config.noise_estimate
        groups = batch.group[rows]
        innovation = ~consensus[groups] if estimate != "innovation" else np.ones(rows.size, bool)
        c = np.where(innovation, self._c, self._c_consensus)
        w = weight[rows] * (1.0 / (c * inflation))  # R_i is kept without the inflation
        u = v = y[:, rows]  # innovation: y y^T - A
        base = a[:, groups]
        if estimate == "consensus":  # r r^T - R_-i
            u = v = np.where(innovation, u, residual[:, rows])
            base = np.where(innovation, base, rest[:, rows])
        elif estimate == "grubbs":  # the prior as the third corner: sym(y r^T)
            v = np.where(innovation, v, residual[:, rows])
            base = np.where(innovation, base, 0.0)
        sample = w * _outer(u, v) - base / inflation
        drone, target = batch.drone[rows], batch.target[rows]
        blended = (1.0 - beta) * self._r[:, drone, target] + beta * sample
        self._r[:, drone, target] = _floor_sym(blended, self._floor)


def _joint_update(mean, covariance, a, lam, b, fading, gate):
    r"""One update of every target's prior ``mean`` ``(G, n)`` / ``covariance`` ``(G, n, n)``
    (position block ``A`` ``(3, G)``) with its weighted measurements in information form,
    ``Lambda = sum_i w_i R~_i^-1`` ``(3, G)`` and ``b = sum_i w_i R~_i^-1 y_i`` ``(2, G)``:
    ``R_bar = Lambda^-1``, ``y_bar = R_bar b``, a lagging track's prior inflated (with
    ``fading``, where ``y_bar`` lies beyond ``gate``), ``K = P^- H^T (A + R_bar)^-1`` and the
    Joseph-form covariance (as :func:`~dronefl.tracking.ekf.position_update`). Returns the
    posterior mean and covariance and the ``A`` used."""
    r_bar = _inv_sym(lam)
    y_bar = _apply(r_bar, b)  # (2, G)
    s_inv = _inv_sym(a + r_bar)
    if fading:
        fused_nis = _quad(y_bar, s_inv)
        lagging = fused_nis > gate
        if lagging.any():  # a lagging track: trust the drones
            factor = np.where(lagging, np.minimum(fused_nis / gate, MAX_FADING), 1.0)
            covariance, a = covariance * factor[:, None, None], a * factor
            s_inv = _inv_sym(a + r_bar)
    k = covariance[:, :, :2] @ _matrix(s_inv)  # K = P^- H^T S^-1, (G, n, 2)
    n = mean.shape[1]
    kh = np.zeros((len(mean), n, n))  # K H
    kh[:, :, :2] = k
    i_kh = np.eye(n) - kh
    mean = mean + (k @ y_bar.T[:, :, None])[:, :, 0]
    return mean, _sandwich(i_kh, covariance) + _sandwich(k, _matrix(r_bar)), a


#: Row and column indices of the components ``(xx, xy, yy)`` of a symmetric 2 x 2 (so
#: ``u[rows] * v[cols]`` are those of ``u v^T``).
_XX_XY_YY = (np.array([0, 0, 1]), np.array([0, 1, 1]))

#: Signs of the cofactors of ``(yy, xy, xx)``: the adjugate of a symmetric 2 x 2.
_COFACTOR_SIGN = np.array([[1.0], [-1.0], [1.0]])


def _matrix(m: np.ndarray) -> np.ndarray:
    """The symmetric matrices of components ``m = (xx, xy, yy)`` ``(3, ...)``,
    ``(..., 2, 2)``."""
    out = np.empty((*m.shape[1:], 2, 2))
    out[..., 0, 0], out[..., 1, 1] = m[0], m[2]
    out[..., 0, 1] = out[..., 1, 0] = m[1]
    return out


def _sandwich(left: np.ndarray, middle: np.ndarray) -> np.ndarray:
    """``L M L^T`` for stacks ``L`` ``(G, n, m)``, ``M`` ``(G, m, m)``."""
    return left @ middle @ left.transpose(0, 2, 1)


def _inv_sym(m: np.ndarray) -> np.ndarray:
    """Inverses of the symmetric matrices of components ``m = (xx, xy, yy)`` ``(3, K)``, as
    components (closed form: ``(yy, -xy, xx) / det``)."""
    det = m[0] * m[2] - m[1] * m[1]
    return m[::-1] * (_COFACTOR_SIGN / det)


def _apply(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``M v`` for symmetric ``M`` of components ``(3, K)`` and vectors ``v`` ``(2, K)``:
    ``(xx v_x + xy v_y, xy v_x + yy v_y)``, ``(2, K)``."""
    return m[:2] * v[0] + m[1:] * v[1]


def _quad(v: np.ndarray, m: np.ndarray) -> np.ndarray:
    """``v^T M v`` ``(K,)`` for vectors ``v`` ``(2, K)`` and symmetric ``M`` of components
    ``(3, K)``."""
    mv = _apply(m, v)
    return v[0] * mv[0] + v[1] * mv[1]


def _outer(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The symmetric part of ``u v^T`` for vectors ``(2, K)``, as components ``(3, K)``."""
    out = u[_XX_XY_YY[0]] * v[_XX_XY_YY[1]]  # (u_x v_x, u_x v_y, u_y v_y)
    if u is not v:  # u_x v_y and u_y v_x differ
        out[1] = 0.5 * (out[1] + u[1] * v[0])
    return out


def _floor_sym(m: np.ndarray, floor: float) -> np.ndarray:
    """:func:`~dronefl.tracking.adaptive.floor_eigenvalues` of every symmetric matrix of
    components ``m = (xx, xy, yy)`` ``(3, K)``, in closed form (the eigenvalues of a symmetric
    2 x 2 are ``mid -+ sqrt(half^2 + xy^2)``)."""
    xx, xy, yy = m
    mid, half = 0.5 * (xx + yy), 0.5 * (xx - yy)
    radius = np.hypot(half, xy)
    kept = mid - radius >= floor
    if kept.all():
        return m
    # eigenvector of the larger eigenvalue: (cos t, sin t) with tan 2t = 2 xy / (xx - yy);
    # a multiple of I (radius 0) becomes floor I
    round_ = radius == 0.0
    safe = np.where(round_, 1.0, radius)
    c2, s2 = np.where(round_, 1.0, half / safe), np.where(round_, 0.0, xy / safe)  # cos, sin 2t
    high = np.maximum(mid + radius, floor)
    mid, half = 0.5 * (high + floor), 0.5 * (high - floor)
    return np.where(kept, m, np.array((mid + half * c2, half * s2, mid - half * c2)))


def _consensus_gate(batch, z, r, info, prior_nis, gate, prior_gate):
    """Gate measurements against each other: for every target with two or more measurements,
    while some leave-one-out residual's ``d^2`` exceeds ``gate``, reject the worst and recompute
    among the rest (a single wild drone must not drag the others' residuals out of the gate);
    a last survivor, like a lone measurement, is judged against the prior (``prior_gate``).
    ``z`` ``(2, K)`` m, ``r`` / ``info`` ``(3, K)`` the rows' ``R~_i`` and its inverse.

    Returns ``(accepted (K,), d^2 (K,), residuals (2, K), residual covariances (3, K),
    consensus (G,))`` (residuals and their covariances from the final set, rejected rows keep
    their last values; ``consensus``: the target's residuals are usable, its final set has two
    or more measurements, all accepted)."""
    group, start = batch.group, batch.start
    accepted = prior_nis <= prior_gate
    nis = prior_nis.copy()
    residual, rest = np.zeros(z.shape), np.zeros(r.shape)
    consensus = batch.count >= 2
    alive = consensus[group]  # the rows still judged against each other
    accepted[alive] = False
    while alive.any():
        rows, e, c = _leave_one_out(batch, z, info, alive)
        residual[:, rows], rest[:, rows] = e, c
        d2 = np.full(len(group), -np.inf)
        d2[rows] = _quad(e, _inv_sym(r[:, rows] + c))
        agree = alive & (np.maximum.reduceat(d2, start) <= gate)[group]
        accepted[agree], nis[agree] = True, d2[agree]
        alive &= ~agree
        if not alive.any():
            break
        # one rejection per target left: the worst, or of two that disagree, the one farther
        # from the prior (the first of equals, as the drone order is fixed)
        pair = (np.add.reduceat(alive, start, dtype=int) == 2)[group]
        badness = np.where(alive, np.where(pair, prior_nis, d2), -np.inf)
        worst = (alive & (badness == np.maximum.reduceat(badness, start)[group])).nonzero()[0]
        worst = worst[np.diff(group[worst], prepend=-1) != 0]  # the first of each target
        nis[worst], alive[worst] = d2[worst], False
        last = alive & pair
        accepted[last] = prior_nis[last] <= prior_gate
        consensus[group[last]], alive[last] = False, False
    return accepted, nis, residual, rest, consensus


def _leave_one_out(batch, z, info, alive):
    r"""Every ``alive`` ``(K,)`` row's residual from the information-weighted mean of the other
    alive rows of its target, ``r_i = z_i - \bar z_{-i}`` (m), and that mean's covariance
    ``\bar R_{-i}`` (m^2), from positions ``z`` ``(2, K)`` and information matrices ``R_i^-1``
    ``(3, K)`` (every target with an alive row has two or more). Returns ``(rows (K',),
    residuals (2, K'), covariances (3, K'))``."""
    rows = alive.nonzero()[0]
    groups = batch.group[rows]
    info_z = _apply(info, z)  # R^-1 z, (2, K)
    total = np.add.reduceat(info * alive, batch.start, axis=1)[:, groups]
    total_z = np.add.reduceat(info_z * alive, batch.start, axis=1)[:, groups]
    rest = _inv_sym(total - info[:, rows])
    return rows, z[:, rows] - _apply(rest, total_z - info_z[:, rows]), rest


#: Largest fading factor applied to a lagging track's prior covariance in one update.
MAX_FADING = 2.0

#: Fusion methods by name (``FusionConfig.method``).
FUSION_METHODS: dict[str, type[FusionMethod]] = {
    "paper": SequentialAdaptive,
    "robust": RobustAdaptive,
}
