"""What a closed-loop episode records and what it reports (paper Table I, SPEC §8).

* :class:`EpisodeLog`: the per-step arrays (truth, predictions, fused tracks, Tr P, cost),
  saved as ``episode.npz``;
* :class:`TrackingMetrics`: Table I's metrics computed from a log by :func:`tracking_metrics`;
* :class:`EpisodeMetrics`: everything ``metrics.json`` holds: what ran, the tracking metrics,
  the FL rounds (:class:`ClosedLoopRound`), the traffic and the timing.
"""

from __future__ import annotations

import zipfile
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from dronefl.accounting import Communication
from dronefl.config import Scenario
from dronefl.io import atomic_savez
from dronefl.serialize import load_result, save_result
from dronefl.tracking.set_distances import SetDistances

#: The file of a deployed episode with the noise reports the cloud received
#: (``noise`` ``(K, M, N, 2, 2)`` m^2, NaN where none came; written by ``deploy up``, read by
#: ``dronefl replay``).
REPORTS_NAME = "reports.npz"


def all_sent(prediction: np.ndarray) -> np.ndarray:
    """``(K, M, N)`` bool: every finite prediction of ``prediction`` ``(K, M, N, 2)`` m, the
    ``sent`` mask of an episode whose drones withheld nothing (and of one recorded before the
    mask existed)."""
    return np.isfinite(prediction).all(axis=-1)


def received_predictions(prediction: np.ndarray, sent: np.ndarray) -> np.ndarray:
    """The predictions ``(K, M, N, 2)`` m as the cloud received them: NaN where ``sent``
    ``(K, M, N)`` is not set."""
    return np.where(sent[..., None], prediction, np.nan)


@dataclass
class EpisodeLog:
    """Per-step arrays of an episode (index k is time ``k dt``); column j is target
    ``scenario.target_ids[j]``, row i drone ``scenario.drone_ids[i]``.

    ``prediction`` holds every prediction a drone made (Table I's prediction error is over
    them all) and ``sent`` which of them went to the cloud: all of them, unless the drones
    withhold the predictions of targets they do not detect at that step
    (``TrackConfig.detected_only``). Left out, ``sent`` is every finite prediction.
    """

    t: np.ndarray  # (K+1,) s
    target_position: np.ndarray  # (K+1, N, 2) true, m
    drone_position: np.ndarray  # (K+1, M, 2) true, m
    drone_velocity: np.ndarray  # (K+1, M, 2) true, m/s
    prediction: np.ndarray  # (K, M, N, 2) drone i's prediction at k of target j at k+1, m
    track_position: np.ndarray  # (K+1, N, 2) fused estimate of time k, m (NaN: no track)
    trace: np.ndarray  # (K, N) Tr P after the update at k, m^2 (+ (m/s)^2)
    cost: np.ndarray  # (K,) planner cost J
    fl_steps: list[int] = field(default_factory=list)
    sent: np.ndarray | None = None  # (K, M, N) bool: prediction (k, i, j) reached the cloud

    def __post_init__(self) -> None:
        if self.sent is None:
            self.sent = all_sent(self.prediction)

    def sent_predictions(self) -> np.ndarray:
        """The predictions as the cloud received them, ``(K, M, N, 2)`` m, NaN where none
        was sent."""
        return received_predictions(self.prediction, self.sent)

    @classmethod
    def empty(cls, scenario: Scenario, n_steps: int) -> EpisodeLog:
        """A log for ``n_steps`` steps of ``scenario``, predictions and tracks NaN."""
        m, n = len(scenario.drones), len(scenario.targets)
        return cls(
            t=np.arange(n_steps + 1) * scenario.dt,
            target_position=np.zeros((n_steps + 1, n, 2)),
            drone_position=np.zeros((n_steps + 1, m, 2)),
            drone_velocity=np.zeros((n_steps + 1, m, 2)),
            prediction=np.full((n_steps, m, n, 2), np.nan),
            track_position=np.full((n_steps + 1, n, 2), np.nan),
            trace=np.full((n_steps, n), np.nan),
            cost=np.zeros(n_steps),
            sent=np.zeros((n_steps, m, n), dtype=bool),
        )

    def state(self) -> dict:
        """The log as arrays and its FL steps, for an episode checkpoint."""
        arrays = {
            f.name: getattr(self, f.name).copy()
            for f in fields(self)
            if isinstance(getattr(self, f.name), np.ndarray)
        }
        return {"arrays": arrays, "fl_steps": list(self.fl_steps)}

    @classmethod
    def from_state(cls, state: dict) -> EpisodeLog:
        """The log a :meth:`state` holds."""
        return cls(**state["arrays"], fl_steps=[int(k) for k in state["fl_steps"]])

    def save(self, path: Path) -> Path:
        """Write the log as ``.npz`` (atomically)."""
        arrays = {k: v for k, v in asdict(self).items() if isinstance(v, np.ndarray)}
        return atomic_savez(path, fl_steps=np.array(self.fl_steps, dtype=np.int64), **arrays)

    @classmethod
    def load(cls, path: Path) -> EpisodeLog:
        """Read a :meth:`save` file; ``OSError`` for a missing or unreadable file,
        ``ValueError`` naming it for a corrupt or foreign one."""
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
        except (ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise ValueError(f"{path}: not a readable episode log ({exc})") from None
        try:
            steps = [int(k) for k in arrays.pop("fl_steps")]
            return cls(**arrays, fl_steps=steps)
        except (KeyError, TypeError) as exc:
            raise ValueError(f"{path}: not an episode log ({exc})") from None


@dataclass(frozen=True)
class TrackingMetrics:
    """Table I's metrics of an episode.

    * ``prediction_error`` (m^2): mean ``||z_hat^i_{j,k+1} - z_{j,k+1}||^2`` over every
      prediction a drone made of an assigned target;
    * ``tracking_distance`` (m^2): mean squared horizontal distance drone to assigned target;
    * ``uncertainty``: mean ``Tr P`` over tracked targets and steps;
    * ``speed_change`` (m/s): mean ``||v_k - v_{k-1}||`` over drones and steps;
    * ``total_cost``: mean planner cost ``J`` per step;
    * ``prediction_coverage``: fraction of (step, drone, assigned target) with a prediction;
    * ``tracking_error`` (m^2): mean squared error of the fused tracks;
    * ``sent_prediction_error`` (m^2): ``prediction_error`` over the predictions the drones
      sent to the cloud, the only ones the fusion sees (every prediction made, unless
      ``drone.detected_only`` withholds those of targets out of view).
    """

    prediction_error: float
    tracking_distance: float
    uncertainty: float
    speed_change: float
    total_cost: float
    prediction_coverage: float
    tracking_error: float
    sent_prediction_error: float


def tracking_metrics(log: EpisodeLog, scenario: Scenario) -> TrackingMetrics:
    """Table I's metrics of ``log`` (see :class:`TrackingMetrics`)."""
    column = {t: j for j, t in enumerate(scenario.target_ids)}
    pred_err, sent_err, track_dist, coverage = [], [], [], []
    for i, drone in enumerate(scenario.drones):
        for target_id in drone.targets:
            j = column[target_id]
            predicted = log.prediction[:, i, j]  # (K, 2)
            truth_next = log.target_position[1:, j]  # (K, 2)
            ok = np.isfinite(predicted).all(axis=1)
            squared = ((predicted - truth_next) ** 2).sum(axis=1)
            pred_err.append(squared[ok])
            sent_err.append(squared[ok & log.sent[:, i, j]])
            coverage.append(ok)
            gap = log.drone_position[:-1, i] - log.target_position[:-1, j]
            track_dist.append((gap**2).sum(axis=1))
    errors, sent = np.concatenate(pred_err), np.concatenate(sent_err)
    speed_change = np.linalg.norm(np.diff(log.drone_velocity[:-1], axis=0), axis=-1)
    return TrackingMetrics(
        prediction_error=float(errors.mean()) if errors.size else float("nan"),
        tracking_distance=float(np.concatenate(track_dist).mean()),
        uncertainty=_nanmean(log.trace),
        speed_change=float(speed_change.mean()),
        total_cost=float(log.cost.mean()),
        prediction_coverage=float(np.concatenate(coverage).mean()),
        tracking_error=_nanmean(((log.track_position - log.target_position) ** 2).sum(axis=-1)),
        sent_prediction_error=float(sent.mean()) if sent.size else float("nan"),
    )


def _nanmean(values: np.ndarray) -> float:
    """``np.nanmean(values)``, but NaN without numpy's empty-slice warning when every entry is
    NaN (e.g. an episode too short for the fusion to hold a track)."""
    return float("nan") if np.isnan(values).all() else float(np.nanmean(values))


@dataclass(frozen=True)
class ClosedLoopRound:
    """One model update of the closed loop: played at simulated time ``t`` (s), taking
    ``seconds`` of wall time; ``train_loss`` per drone (``0`` = the cloud) in m^2 (scaled
    MSE of the training windows); ``rejected`` the drones whose update was left out and why;
    ``weight_bytes`` per drone, down and up."""

    round: int
    t: float
    seconds: float
    train_loss: dict[int, float]
    rejected: tuple[str, ...] = ()
    weight_bytes_down: dict[int, int] = field(default_factory=dict)
    weight_bytes_up: dict[int, int] = field(default_factory=dict)


@dataclass(frozen=True)
class EpisodeMetrics:
    """Everything ``metrics.json`` holds about one closed-loop episode.

    ``scenario`` is its name and ``scenario_hash`` the content hash of the scenario that ran;
    ``tracking`` Table I's metrics; ``set_distances`` the fused tracks' OSPA and GOSPA (m);
    ``sim_seconds`` / ``wall_seconds`` / ``fl_seconds`` in s; ``planner_ms_per_step`` in ms;
    ``gating_rejections`` and ``track_resets`` counts of the fusion; ``centralized_inputs`` says in
    words what the centralized baseline's drones sent (``None`` for the other methods); ``config``
    the episode's settings as given; ``model_input`` what the method's model reads (``boxes`` or
    ``frames``) and ``model_parameters`` its trainable parameters (``None``: not recorded, as by
    a deployment)."""

    scenario: str
    scenario_hash: str
    method: str
    seed: int
    environment: str
    detector: str
    labels: str
    tracking: TrackingMetrics
    set_distances: SetDistances
    fl_rounds: tuple[ClosedLoopRound, ...]
    communication: Communication
    sim_seconds: float
    wall_seconds: float
    fl_seconds: float
    planner_ms_per_step: float
    gating_rejections: int
    track_resets: int
    centralized_inputs: str | None
    config: dict[str, str | int | float | bool]
    model_input: str = field(default="boxes", kw_only=True)
    model_parameters: int | None = field(default=None, kw_only=True)

    @property
    def realtime_factor(self) -> float:
        """Simulated seconds per wall second."""
        return self.sim_seconds / self.wall_seconds

    def save(self, path: Path) -> Path:
        """Write ``metrics.json`` atomically."""
        return save_result(path, self)

    @classmethod
    def load(cls, path: Path) -> EpisodeMetrics:
        """Read a ``metrics.json``; a corrupt or foreign file raises naming the file."""
        return load_result(cls, path)
