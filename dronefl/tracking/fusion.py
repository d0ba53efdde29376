"""Multi-drone fusion in the cloud: one adaptive EKF per target fed by every drone's predictions.

Each step the drones send their predicted positions of the targets they see
(:class:`PositionMeasurement`); :meth:`Fuser.update` propagates every track to the time those
predictions refer to, fuses them (each with its pair's adapted ``R``, gated; the step's
measurements go to the fusion method as one :class:`~dronefl.tracking.methods.MeasurementBatch`)
and returns the fused :class:`Track` of every target. A target that nobody reports is only
predicted. :meth:`Fuser.forecast` hands the planner a :class:`TrackForecast`:
the fused positions and, for any set of observing drones, the trace of the covariance after the
next predict + update.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING

import numpy as np

from dronefl.tracking.config import TEMPORAL_KERNEL, FusionConfig
from dronefl.tracking.ekf import inv2_stack
from dronefl.tracking.methods import FUSION_METHODS, MeasurementBatch
from dronefl.tracking.models import ConstantVelocity
from dronefl.tracking.smoother import SmoothedTrack, TrackHistory, rts_smooth

if TYPE_CHECKING:
    from dronefl.config import Scenario
    from dronefl.settings import FusionSetting


@dataclass(frozen=True)
class PositionMeasurement:
    """Drone ``drone_id``'s predicted ground ``position`` ``(2,)`` (m, world frame) of target
    ``target_id``; the time it refers to is the ``t`` of the :meth:`Fuser.update` call.
    ``reported_noise`` ``(2, 2)`` m²: the drone's own estimate of its error on this target
    (:mod:`dronefl.tracking.reports`), ``None`` when it sends none."""

    drone_id: int
    target_id: int
    position: np.ndarray
    reported_noise: np.ndarray | None = None


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
        s_inv = inv2_stack(m) @ lam  # S_A^-1, (2^k, 2, 2)
        reduction = np.einsum("mij,ji->m", s_inv, self._btb[target_index])  # Tr(S^-1 B^T B)
        return self._prior_trace[target_index] - reduction

    def trace_after(self, target_id: int, drone_ids: Sequence[int]) -> float:
        """``Tr P^+`` of target ``target_id`` after updates from ``drone_ids`` (may be empty)."""
        j = self.target_ids.index(target_id)
        idx = [self.drone_ids.index(i) for i in drone_ids]
        return float(self.trace_table(j, idx)[-1])


class Fuser:
    r"""Cloud-side fusion of every drone's target predictions (SPEC §6).

    One filter per target ``j`` (state and covariance of the configured motion model) and one
    noise ``R_ij`` per (drone, target) pair, owned by the configured
    :class:`~dronefl.tracking.methods.FusionMethod`. An update at time ``t`` predicts every track
    from the previous update to ``t``,

    .. math::
        x_j^- = f(x_j, \Delta t),\qquad P_j^- = F P_j F^T + Q

    then hands the measurements of every tracked target (in drone-id order) to the method in
    one :class:`~dronefl.tracking.methods.MeasurementBatch`, which fuses them with the pairs'
    adapted ``R`` and gating (``paper``: sequentially; ``robust``: jointly against the common
    prior, Huber-weighted, all targets at once).

    ``target_ids`` / ``drone_ids``: the scenario's ids; ``config``: :class:`FusionConfig`;
    ``initial_positions``: optional ``{target_id: (2,)}`` m to start tracks at ``t0`` (with
    position std ``initial_noise_std``); other targets get a track at their first measurement
    (the mean of that step's positions). With :attr:`FusionConfig.temporal_kernel` it keeps
    each pair's fused positions of the last ``L`` updates. Counters:
    :attr:`rejections` (gated-out measurements), :attr:`measurements` (all fused or gated
    ones), :attr:`resets` (tracks re-initialised after ``reset_after`` all-rejected updates),
    :attr:`dropped` (non-finite measurements ignored).

    With ``record`` (default) every update's prior, transition and posterior are kept, so that
    :meth:`history` and :meth:`smooth` can give the RTS-smoothed tracks of the whole past at
    any time (the pseudo-labels of an FL round).
    """

    def __init__(
        self,
        target_ids: Sequence[int],
        drone_ids: Sequence[int],
        config: FusionConfig | None = None,
        initial_positions: Mapping[int, np.ndarray] | None = None,
        t0: float = 0.0,
        record: bool = True,
    ) -> None:
        self.config = config or FusionConfig()
        self.target_ids = tuple(int(j) for j in target_ids)
        self.drone_ids = tuple(int(i) for i in drone_ids)
        if len(set(self.target_ids)) != len(self.target_ids) or not self.target_ids:
            raise ValueError(f"target_ids must be non-empty and unique, got {self.target_ids}")
        if len(set(self.drone_ids)) != len(self.drone_ids) or not self.drone_ids:
            raise ValueError(f"drone_ids must be non-empty and unique, got {self.drone_ids}")
        self.model = self.config.motion_model()
        self.method = FUSION_METHODS[self.config.method](
            self.config, len(self.drone_ids), len(self.target_ids)
        )
        self.t = float(t0)
        self.record = record
        self._target_index = {j: k for k, j in enumerate(self.target_ids)}
        self._drone_index = {i: k for k, i in enumerate(self.drone_ids)}
        n, n_targets = self.model.ndim, len(self.target_ids)
        self._mean = np.zeros((n_targets, n))
        self._cov = np.zeros((n_targets, n, n))
        self._alive = np.zeros(n_targets, dtype=bool)
        self._misses = np.zeros(n_targets, dtype=int)
        self._last: dict[int, tuple[int, int]] = {}
        self._history: list[list[tuple]] = [[] for _ in self.target_ids]
        self._pending: dict[int, tuple] = {}  # this update's (t, prior mean, prior cov, F)
        kernel = self.config.temporal_kernel
        self._kernel = None if kernel is None else np.asarray(kernel)
        # the fused positions of the last L updates per pair, newest first, (L, D, T, 2) m
        self._recent = np.full((len(kernel or ()), len(self.drone_ids), n_targets, 2), np.nan)
        self._output: dict[int, np.ndarray] = {}  # target index -> the kernel's position
        self.rejections = 0
        self.measurements = 0
        self.resets = 0
        self.dropped = 0
        r0 = self.config.initial_noise_std**2 * np.eye(2)
        for j, position in (initial_positions or {}).items():
            if j not in self._target_index:
                raise ValueError(f"initial_positions: unknown target {j}")
            self._start(self._target_index[j], np.asarray(position, dtype=float), r0, 0)

    def state(self) -> dict:
        """Everything the fusion carries from one update to the next, as arrays and plain
        values (every track, each pair's adapted ``R``, the recorded forward pass stacked per
        target, the temporal kernel's recent positions, the counters), for an episode
        checkpoint; :meth:`restore` takes it back."""
        return {
            "t": self.t,
            "mean": self._mean.copy(),
            "covariance": self._cov.copy(),
            "alive": self._alive.copy(),
            "misses": self._misses.copy(),
            "last": dict(self._last),
            "history": [_history_arrays(self.history(j)) for j in self.target_ids]
            if self.record
            else None,
            "recent": self._recent.copy(),
            "output": {k: v.copy() for k, v in self._output.items()},
            "counters": [self.rejections, self.measurements, self.resets, self.dropped],
            "method": self.method.state(),
        }

    def restore(self, state: dict) -> None:
        """Continue from ``state`` (:meth:`state` of a Fuser of the same ids and config)."""
        self.t = float(state["t"])
        self._mean, self._cov = state["mean"].copy(), state["covariance"].copy()
        self._alive, self._misses = state["alive"].copy(), state["misses"].copy()
        self._last = {int(j): (int(a), int(r)) for j, (a, r) in state["last"].items()}
        if self.record:
            self._history = [
                _history_rows(_history_of(j, rows))
                for j, rows in zip(self.target_ids, state["history"], strict=True)
            ]
        self._recent = state["recent"].copy()
        self._output = {int(k): v.copy() for k, v in state["output"].items()}
        self.rejections, self.measurements, self.resets, self.dropped = (
            int(c) for c in state["counters"]
        )
        self.method.restore(state["method"])

    def _start(self, j: int, position: np.ndarray, position_covariance: np.ndarray, n: int) -> None:
        """(Re)start target index ``j``'s track at ``position`` (a new history segment)."""
        if position.shape != (2,) or not np.isfinite(position).all():
            raise ValueError(f"a track needs a finite (2,) position, got {position}")
        mean, cov = self.model.initial(position, position_covariance, self.config.initial_speed_std)
        self._mean[j], self._cov[j], self._alive[j], self._misses[j] = mean, cov, True, 0
        if self.record:
            self._history[j].append((self.t, mean, cov, None, mean, cov, n))

    def measurement_noise(self, drone_id: int, target_id: int) -> np.ndarray:
        """The current (adapted) ``R`` ``(2, 2)`` m^2 of the pair."""
        return self.method.noise()[self._drone_index[drone_id], self._target_index[target_id]]

    @property
    def tracks(self) -> dict[int, Track]:
        """Current track of every target that has one, by target id."""
        means, covariances = self._mean.copy(), self._cov.copy()  # the tracks' own arrays
        out = {}
        for k in self._alive.nonzero()[0].tolist():
            j = self.target_ids[k]
            accepted, rejected = self._last.get(j, (0, 0))
            mean = means[k]
            if k in self._output:
                mean[:2] = self._output[k]
            velocity = self.model.velocity(mean)
            out[j] = Track(j, self.t, mean, covariances[k], velocity, accepted, rejected)
        return out

    def update(self, t: float, measurements: Sequence[PositionMeasurement]) -> dict[int, Track]:
        """Predict every track to ``t`` (s, the time the predicted positions refer to; never
        before the previous update) and fuse ``measurements``; returns :attr:`tracks`.

        Raises ``ValueError`` for an unknown drone or target id or two measurements of one
        pair; non-finite positions are dropped and counted in :attr:`dropped`.
        """
        if not t >= self.t:
            raise ValueError(f"update time {t} s is before the last update at {self.t} s")
        batch = self._group(measurements)
        self._predict(t - self.t)
        self.t = float(t)
        self._last = {}
        tracked = self._alive[batch.targets]  # (G,)
        for g in (~tracked).nonzero()[0]:
            rows = batch.rows(g)
            self._birth(int(batch.targets[g]), batch.drone[rows], batch.position[rows])
        used = ~tracked[batch.group]  # the rows fused: those of a birth, and those accepted
        if tracked.any():
            used[tracked[batch.group]] = self._fuse(
                batch if tracked.all() else batch.select(tracked)
            )
        if self._kernel is not None:
            self._apply_kernel(batch.drone[used], batch.target[used], batch.position[used])
        if self.record:
            measured = set(batch.targets.tolist())
            for j in self._alive.nonzero()[0].tolist():
                if j not in measured:
                    row = (self._mean[j].copy(), self._cov[j].copy(), 0)
                    self._history[j].append(self._pending[j] + row)
        return self.tracks

    def _predict(self, dt: float) -> None:
        """Propagate every live track ``dt`` s; keeps each prior for the history."""
        alive = self._alive.nonzero()[0]
        if dt == 0 or alive.size == 0:
            jacobians = [np.eye(self.model.ndim)] * alive.size
        elif isinstance(self.model, ConstantVelocity):  # linear: one F and Q for every track
            f = self.model.transition_matrix(dt)
            q = self.model.process_noise(self._mean[0], dt)
            self._mean[alive] = self._mean[alive] @ f.T
            self._cov[alive] = f @ self._cov[alive] @ f.T + q
            jacobians = [f] * alive.size
        else:
            jacobians = []
            for j in alive:
                x = self._mean[j]
                f = self.model.jacobian(x, dt)
                jacobians.append(f)
                self._cov[j] = f @ self._cov[j] @ f.T + self.model.process_noise(x, dt)
                self._mean[j] = self.model.transition(x, dt)
        if self.record:  # this update's (t, prior mean, prior cov, F) per live track
            t, means, covariances = self.t + dt, self._mean[alive], self._cov[alive]  # copies
            self._pending = {
                j: (t, means[row], covariances[row], f)
                for row, (j, f) in enumerate(zip(alive.tolist(), jacobians, strict=True))
            }

    def _group(self, measurements: Sequence[PositionMeasurement]) -> MeasurementBatch:
        """The finite ``measurements`` as a batch (rows in target, then drone order: a fixed
        order makes runs reproducible); counts the others in :attr:`dropped`."""
        pairs = [
            (self._drone_index.get(m.drone_id), self._target_index.get(m.target_id))
            for m in measurements
        ]
        if any(None in pair for pair in pairs):
            m = next(m for m, pair in zip(measurements, pairs, strict=True) if None in pair)
            raise ValueError(
                f"measurement from drone {m.drone_id} of target {m.target_id}: unknown id "
                f"(drones {self.drone_ids}, targets {self.target_ids})"
            )
        if len(set(pairs)) < len(pairs):
            m = next(m for k, m in enumerate(measurements) if pairs[k] in pairs[:k])
            raise ValueError(
                f"two measurements from drone {m.drone_id} of target {m.target_id} in one update"
            )
        index = np.array(pairs, dtype=int).reshape(-1, 2)  # (drone, target) per row, (K, 2)
        positions = _positions(measurements)
        reported = _reported(measurements)
        finite = np.isfinite(positions).all(axis=1)
        if not finite.all():
            self.dropped += len(finite) - int(finite.sum())
            index, positions, reported = index[finite], positions[finite], reported[finite]
        return MeasurementBatch.of(index[:, 1], index[:, 0], positions, reported)

    def _birth(self, j: int, drones: np.ndarray, positions: np.ndarray) -> None:
        """Start (or restart) target ``j``'s track at the mean of ``positions``; its
        covariance is that of the mean of independent measurements, ``(sum_i
        R_ij^-1)^-1``."""
        noise = self.method.noise()[drones, j]
        info = np.linalg.inv(noise).sum(axis=0)
        self._start(j, positions.mean(axis=0), np.linalg.inv(info), len(drones))
        self._last[self.target_ids[j]] = (len(drones), 0)

    def _apply_kernel(self, drone: np.ndarray, target: np.ndarray, position: np.ndarray) -> None:
        """Remember this update's fused measurements (``drone`` / ``target`` indices ``(K,)``,
        ``position`` ``(K, 2)`` m) and set :attr:`_output`, the kernel's position of every
        live target that a drone sent at each of the last ``L`` updates
        (:attr:`FusionConfig.temporal_kernel`): ``sum_l w_l m_{t-l}``, with ``m_{t-l} = (sum_i
        R_i^-1)^-1 sum_i R_i^-1 z_i(t-l)`` over those drones ``i`` and their current ``R``."""
        self._recent[1:] = self._recent[:-1].copy()
        self._recent[0] = np.nan
        self._recent[0, drone, target] = position
        full = np.isfinite(self._recent[..., 0]).all(axis=0)  # (D, T)
        self._output = {}
        live = (full.any(axis=0) & self._alive).nonzero()[0]
        if not live.size:
            return
        noise = self.method.noise()
        for k in live.tolist():
            drones = full[:, k].nonzero()[0]
            info = np.linalg.inv(noise[drones, k])  # R_i^-1, (n, 2, 2)
            smoothed = np.einsum("l,lnx->nx", self._kernel, self._recent[:, drones, k])
            self._output[k] = np.linalg.solve(
                info.sum(axis=0), np.einsum("nab,nb->a", info, smoothed)
            )

    def _fuse(self, batch: MeasurementBatch) -> np.ndarray:
        """Fuse ``batch`` (of tracked targets only) into the tracks; count the gated-out
        measurements, reset the tracks lost for ``reset_after`` updates, record the rest.
        Returns the rows fused ``(K,)`` (those not gated out)."""
        j = batch.targets
        result = self.method.update(batch, self._mean[j], self._cov[j])
        self._mean[j], self._cov[j] = result.mean, result.covariance
        accepted = np.add.reduceat(result.accepted.astype(int), batch.start)  # (G,)
        rejected = batch.count - accepted
        self.measurements += len(batch.target)
        self.rejections += int(rejected.sum())
        self._misses[j] = np.where(accepted == 0, self._misses[j] + 1, 0)
        reset_after = self.config.reset_after
        for g, (k, n_accepted, n_rejected) in enumerate(
            zip(j.tolist(), accepted.tolist(), rejected.tolist(), strict=True)
        ):
            target_id = self.target_ids[k]
            self._last[target_id] = (n_accepted, n_rejected)
            if reset_after is not None and self._misses[k] >= reset_after:
                self.resets += 1
                rows = batch.rows(g)
                self._birth(k, batch.drone[rows], batch.position[rows])
                self._last[target_id] = (0, n_rejected)
            elif self.record:  # result's rows are fresh arrays, kept as they are
                row = (result.mean[g], result.covariance[g], n_accepted)
                self._history[k].append(self._pending[k] + row)
        return result.accepted

    def history(self, target_id: int) -> TrackHistory | None:
        """The recorded forward pass of ``target_id``'s track (``None`` before its birth)."""
        if not self.record:
            raise ValueError("this Fuser was made with record=False: it keeps no history")
        rows = self._history[self._target_index[target_id]]
        if not rows:
            return None
        n = self.model.ndim
        eye = np.eye(n)
        return TrackHistory(
            target_id=target_id,
            t=np.array([r[0] for r in rows]),
            prior_mean=np.array([r[1] for r in rows]),
            prior_covariance=np.array([r[2] for r in rows]),
            transition=np.array([eye if r[3] is None else r[3] for r in rows]),
            mean=np.array([r[4] for r in rows]),
            covariance=np.array([r[5] for r in rows]),
            start=np.array([r[3] is None for r in rows]),
            accepted=np.array([r[6] for r in rows], dtype=int),
        )

    def smooth(self) -> dict[int, SmoothedTrack]:
        """The RTS-smoothed track (:func:`~dronefl.tracking.smoother.rts_smooth`) of every
        target that has a history, over all updates so far."""
        out = {}
        for j in self.target_ids:
            history = self.history(j)
            if history is not None:
                out[j] = rts_smooth(history)
        return out

    def forecast(self, dt: float) -> TrackForecast:
        """The planner's view (:class:`TrackForecast`) of the tracked targets (the positions
        the temporal kernel's where it applies, as :attr:`tracks`), with the covariance
        propagated ``dt`` s (one planning step) ahead of the current tracks."""
        if not dt > 0:
            raise ValueError(f"forecast needs dt > 0 s, got {dt}")
        index = np.flatnonzero(self._alive)
        ids = tuple(self.target_ids[k] for k in index)
        n = self.model.ndim
        positions = self._mean[index, :2].copy()
        for row, k in enumerate(index.tolist()):
            if k in self._output:  # the temporal kernel's
                positions[row] = self._output[k]
        predicted = np.zeros((len(ids), n, n))
        for row, k in enumerate(index):
            f = self.model.jacobian(self._mean[k], dt)
            predicted[row] = f @ self._cov[k] @ f.T + self.model.process_noise(self._mean[k], dt)
        noise = self.method.noise()[:, index]
        return TrackForecast(ids, self.drone_ids, positions, predicted, noise)


def _history_arrays(history: TrackHistory | None) -> dict | None:
    """One target's recorded forward pass as arrays (``None``: not born yet)."""
    if history is None:
        return None
    return {f.name: getattr(history, f.name) for f in fields(history) if f.name != "target_id"}


def _history_of(target_id: int, arrays: dict | None) -> TrackHistory | None:
    """:func:`_history_arrays` back as a :class:`TrackHistory` of ``target_id``."""
    return None if arrays is None else TrackHistory(target_id=target_id, **arrays)


def _history_rows(history: TrackHistory | None) -> list[tuple]:
    """:class:`Fuser`'s rows of one target from its stacked ``history`` (``None``: no rows),
    each ``(t, prior mean, prior covariance, F or None at a segment start, mean, covariance,
    accepted)`` as :meth:`Fuser.update` appends them."""
    if history is None:
        return []
    h = history
    return [
        (float(h.t[s]), h.prior_mean[s], h.prior_covariance[s],
         None if h.start[s] else h.transition[s], h.mean[s], h.covariance[s], int(h.accepted[s]))
        for s in range(len(h))
    ]  # fmt: skip


def update_filters(
    fuser: Fuser, label_fuser: Fuser | None, t: float, measurements: Sequence[PositionMeasurement]
) -> tuple[dict[int, Track], dict[int, Track]]:
    """One update at ``t`` s of the planner's ``fuser`` and, when there is a second one, of the
    fusion's own ``label_fuser`` with the same ``measurements``: ``(tracks, fused)``, the
    planner's tracks and those of the filter whose history gives the labels and whose ``Tr P``
    the planner weighs (the same dict with one filter)."""
    tracks = fuser.update(t, measurements)
    if label_fuser is None:
        return tracks, tracks
    return tracks, label_fuser.update(t, measurements)


def planner_forecast(
    fuser: Fuser, label_fuser: Fuser | None, tracks: dict[int, Track], dt: float
) -> TrackForecast:
    """The planner's view of the targets ``dt`` s ahead: ``fuser``'s forecast; with a second
    filter (``label_fuser``, the fusion's own, whose smoothed history gives the labels) the
    positions of ``tracks`` (the step's update of the planner's ``fuser``) with the covariances
    and noises of ``label_fuser``, so that the uncertainty the planner trades against distance
    stays the fusion's."""
    if label_fuser is None:
        return fuser.forecast(dt)
    view = label_fuser.forecast(dt)
    for k, target in enumerate(view.target_ids):
        if target in tracks:
            view.positions[k] = tracks[target].position
    return view


def _positions(measurements: Sequence[PositionMeasurement]) -> np.ndarray:
    """The measurements' positions ``(K, 2)`` m; ``ValueError`` if one is not ``(2,)``."""
    if not measurements:
        return np.empty((0, 2))
    try:
        positions = np.array([m.position for m in measurements], dtype=float)
    except ValueError:  # ragged
        positions = None
    if positions is None or positions.shape != (len(measurements), 2):
        shape = next(s for m in measurements if (s := np.shape(m.position)) != (2,))
        raise ValueError(f"measurement position must have shape (2,), got {shape}")
    return positions


def _reported(measurements: Sequence[PositionMeasurement]) -> np.ndarray:
    """The measurements' reported noises as ``(xx, xy, yy)`` rows ``(K, 3)`` m² (NaN: none)."""
    out = np.full((len(measurements), 3), np.nan)
    for k, m in enumerate(measurements):
        if m.reported_noise is not None:
            noise = np.asarray(m.reported_noise, dtype=float)
            if noise.shape != (2, 2):
                raise ValueError(f"measurement reported_noise must be (2, 2), got {noise.shape}")
            out[k] = noise[0, 0], noise[0, 1], noise[1, 1]
    return out


#: The velocity time constant (s) of the ``robust`` fusion's mean-reverting motion model for
#: random-walk targets: the best smoothed labels among 0.1-5 s on tuning episodes, fused tracks
#: within 10 % of the best (docs/fusion.md).
RANDOM_WALK_VELOCITY_TIME_CONSTANT = 0.25
#: The process noise q (m^2/s^3) for random-walk targets, whose velocity jumps by N(0, 1) m/s
#: per axis every second.
RANDOM_WALK_PSD = 1.0


@dataclass(frozen=True)
class CloudFusion:
    """The cloud's filters for one scenario: ``fusion``, the settings of the filter whose
    smoothed history gives the labels and whose ``Tr P`` the planner weighs, and ``planner``,
    those of a second filter fed the same measurements whose tracks the planner flies on
    (``None``: the planner flies on the first)."""

    fusion: FusionConfig
    planner: FusionConfig | None = None

    @property
    def tracks(self) -> FusionConfig:
        """The settings of the filter whose tracks the planner flies on and the log records."""
        return self.fusion if self.planner is None else self.planner


def cloud_fusion(setting: FusionSetting, reported: bool, scenario: Scenario) -> CloudFusion:
    """The one place a setting becomes the cloud's filters (``track``, the deployed cloud and
    ``replay`` all call it), for ``scenario`` with ``reported`` noise from the drones.

    Constant-speed targets get the constant-velocity model with q =
    ``setting.constant_speed_psd``. Random-walk targets change velocity by about 1 m/s every
    second: they get q = :data:`RANDOM_WALK_PSD`, and the ``robust`` fusion tracks them with a
    velocity that forgets itself over :data:`RANDOM_WALK_VELOCITY_TIME_CONSTANT` s (a track no
    drone sees stops instead of carrying the velocity it had at the edge of the view on);
    there, the planner flies on a second filter of q = ``setting.random_walk_planner_psd``
    (when set), and with ``setting.temporal_kernel`` the tracks it flies on are
    :data:`TEMPORAL_KERNEL`'s (fitted on random-walk targets). The ``paper`` fusion keeps the
    constant-velocity model. One scenario with a random-walk target sets the model for all."""
    random_walk = any(t.motion == "random_walk" for t in scenario.targets)
    noise_split = "reported" if reported else "adaptive"
    kernel = TEMPORAL_KERNEL if setting.temporal_kernel and random_walk else None
    base = {"method": setting.method, "noise_split": noise_split, "temporal_kernel": kernel}
    if not random_walk:
        return CloudFusion(FusionConfig(**base, acceleration_psd=setting.constant_speed_psd))
    if setting.method == "robust":
        fusion = FusionConfig(
            **base,
            acceleration_psd=RANDOM_WALK_PSD,
            motion="mean_reverting",
            velocity_time_constant=RANDOM_WALK_VELOCITY_TIME_CONSTANT,
        )
    else:
        fusion = FusionConfig(**base, acceleration_psd=RANDOM_WALK_PSD)
    q = setting.random_walk_planner_psd
    return CloudFusion(fusion, None if q is None else replace(fusion, acceleration_psd=q))
