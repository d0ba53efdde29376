"""Replay: re-fuse and smooth an episode's recorded predictions with any setting.

``dronefl track`` saves every drone's prediction of every target (``episode.npz``: arrays
``prediction`` ``(K, M, N, 2)``, ``target_position`` and ``track_position`` ``(K+1, N, 2)``,
``t`` ``(K+1,)``; ``metrics.json`` names the scenario and holds the setting it flew).
:func:`replay_setting` feeds the same stream to the cloud's filters as a setting makes them
(:func:`~dronefl.tracking.fusion.cloud_fusion`), makes the pseudo-labels of the whole
episode, and compares, per target, the fused (filtered) track and the labels with each
drone's own predictions, all against the truth; :func:`replay` does the same with any
filters (:class:`~dronefl.tracking.fusion.CloudFusion`). The drones flew under the recorded
episode's fusion, so a replay changes the estimates, not the flight.

What a setting has the drones send beyond what they sent in flight is rebuilt from their
onboard records in the episode's checkpoint (:func:`episode_records`): the noise reports
(:func:`drone_reports`) and the bias correction from the boxes and odometry each drone
stored, the same data from which it would have computed them in flight, and with
``drone.detected_only`` only the predictions made while the drone detected the target.

A ``dronefl deploy up`` folder replays too: its ``episode.npz`` holds the predictions the cloud
received and its ``reports.npz`` (:data:`REPORTS_NAME`) the noise reports that came with
them, which are used as they are (the drones' onboard records stay on the drones).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from dronefl.config import Scenario, load_scenario
from dronefl.experiments.loop_checkpoint import CHECKPOINT_NAME, read_loop_checkpoint
from dronefl.fl.checkpoint import CheckpointError
from dronefl.io import atomic_write_json, atomic_write_text
from dronefl.models.online import OnboardRecord
from dronefl.results.episode import REPORTS_NAME, all_sent, received_predictions
from dronefl.settings import Setting, SettingError
from dronefl.tracking import Fuser, PositionMeasurement
from dronefl.tracking.fusion import CloudFusion, cloud_fusion, update_filters
from dronefl.tracking.labels import DEFAULT_MAX_STD, make_labels
from dronefl.tracking.reports import (
    forecast_residual_reports,
    ground_plane,
    record_ground_positions,
)


class EpisodeError(ValueError):
    """A missing or malformed episode folder (names the file)."""


@dataclass(frozen=True)
class Episode:
    """What a replay needs from a recorded episode (index ``k`` of the time grid is ``k dt``).

    ``prediction`` ``(K, M, N, 2)`` m: drone ``i``'s prediction at step ``k`` of target ``j``'s
    position at ``k + 1`` (NaN: none); ``target_position`` ``(K+1, N, 2)`` m: the truth;
    ``track_position`` ``(K+1, N, 2)`` m: the planner's tracks as flown; ``t`` ``(K+1,)`` s;
    ``sent`` ``(K, M, N)`` bool: which predictions reached the cloud; ``setting`` the setting
    it was flown with (``None`` for an episode that does not record one);
    ``received_reports`` ``(K, M, N, 2, 2)`` m^2 the noise reports a deployed cloud received
    (:data:`REPORTS_NAME`; ``None`` for a ``track`` episode), whose ``prediction`` then holds
    what the cloud received: nothing is withheld from it or rebuilt.
    """

    path: Path
    scenario: Scenario
    prediction: np.ndarray
    target_position: np.ndarray
    track_position: np.ndarray
    t: np.ndarray
    sent: np.ndarray | None = None
    setting: Setting | None = None
    received_reports: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.sent is None:
            object.__setattr__(self, "sent", all_sent(self.prediction))

    @property
    def bias_corrected(self) -> bool:
        """Whether the drones corrected their predictions' bias in flight (the predictions
        recorded are those they sent)."""
        return self.setting is not None and self.setting.drone.correct_bias

    @property
    def withheld(self) -> bool:
        """Whether the drones sent only what they detected in flight (``sent`` says so)."""
        return self.setting is not None and self.setting.drone.detected_only


def load_episode(folder: str | Path) -> Episode:
    """Read ``episode.npz`` and the scenario and setting ``metrics.json`` records in
    ``folder``."""
    folder = Path(folder)
    npz, meta = folder / "episode.npz", folder / "metrics.json"
    for path in (npz, meta):
        if not path.is_file():
            raise EpisodeError(
                f"{path}: not found (is {folder} a `dronefl track` or `deploy up` folder?)"
            )
    try:
        config = json.loads(meta.read_text())["config"]
        name = str(config["scenario"])
    except (ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
        raise EpisodeError(f"{meta}: no config naming the scenario ({exc})") from None
    scenario = load_scenario(name)
    setting = None
    if "setting_values" in config:
        try:
            setting = Setting.from_dict(config["setting_values"], str(config.get("setting_name")))
        except SettingError as exc:
            raise EpisodeError(f"{meta}: {exc}") from None
    try:
        with np.load(npz, allow_pickle=False) as data:
            arrays = {k: np.asarray(data[k], dtype=float) for k in _ARRAYS}
            sent = np.asarray(data["sent"], dtype=bool) if "sent" in data else None
    except (OSError, ValueError, KeyError, EOFError) as exc:
        raise EpisodeError(f"{npz}: unreadable or missing an array ({exc})") from None
    except Exception as exc:  # a damaged zip raises zipfile's own errors
        raise EpisodeError(f"{npz}: not a readable episode ({type(exc).__name__})") from None
    k, m, n = arrays["prediction"].shape[:3]
    expected = {
        "prediction": (k, len(scenario.drones), len(scenario.targets), 2),
        "target_position": (k + 1, n, 2),
        "track_position": (k + 1, n, 2),
        "t": (k + 1,),
    }
    for key, shape in expected.items():
        if arrays[key].shape != shape:
            raise EpisodeError(f"{npz}: {key} has shape {arrays[key].shape}, expected {shape}")
    if k < 1:
        raise EpisodeError(f"{npz}: holds no step")
    if sent is not None and sent.shape != expected["prediction"][:3]:
        shape = expected["prediction"][:3]
        raise EpisodeError(f"{npz}: sent has shape {sent.shape}, expected {shape}")
    received = _received_reports(folder / REPORTS_NAME, (k, m, n, 2, 2))
    return Episode(
        folder, scenario, **arrays, sent=sent, setting=setting, received_reports=received
    )


def _received_reports(path: Path, shape: tuple[int, ...]) -> np.ndarray | None:
    """A deployed episode's noise reports (:data:`REPORTS_NAME`), ``None`` if ``path`` is not
    there; :class:`EpisodeError` names the file if it is unreadable or of another shape."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            noise = np.asarray(data["noise"], dtype=float)
    except Exception as exc:  # unreadable, truncated, or without the array
        raise EpisodeError(f"{path}: unreadable or without its noise array ({exc})") from None
    if noise.shape != shape:
        raise EpisodeError(f"{path}: noise has shape {noise.shape}, expected {shape}")
    return noise


_ARRAYS = ("prediction", "target_position", "track_position", "t")


@dataclass(frozen=True)
class DroneError:
    """One drone's own predictions of a target: mean squared error ``mse`` (m^2) against the
    truth one step later, over its ``n`` predictions."""

    drone_id: int
    mse: float
    n: int


@dataclass(frozen=True)
class TargetReplay:
    """One target in a replay. MSEs in m^2 against the truth.

    ``drones``: every drone that predicted it (:class:`DroneError`); ``fused_mse``: the
    re-fused filtered track over every step it existed; ``fused_mse_paired``: the same over the
    steps the best drone predicted (the two MSEs of :attr:`fused_over_best` then cover the same
    steps); ``label_mse`` over the ``label_kept``
    fraction of steps that got a label; ``recorded_mse``: the track as flown;
    ``oracle_mse_paired``: the best fixed weighting of the drones' predictions, fitted to the
    truth afterwards, over the best drone's steps (:func:`oracle_weighting_mse`; a reference
    for what a fusion with fixed weights could reach, not an estimator);
    ``temporal_oracle_over_best`` and ``temporal_oracle_steps``: the same for the best linear
    combination of the drones' last :data:`TEMPORAL_TAPS` predictions, against the best drone
    on the steps where all of them exist, and ``temporal_oracle_overall`` over all the best
    drone's steps (:func:`temporal_oracle`).
    """

    target_id: int
    drones: tuple[DroneError, ...]
    fused_mse: float
    fused_mse_paired: float
    label_mse: float
    label_kept: float
    recorded_mse: float
    oracle_mse_paired: float = float("nan")
    temporal_oracle_over_best: float = float("nan")
    temporal_oracle_steps: int = 0
    temporal_oracle_overall: float = float("nan")

    @property
    def best_drone_mse(self) -> float:
        """The best single drone's prediction MSE of this target, m^2 (NaN if none)."""
        return min((d.mse for d in self.drones), default=float("nan"))

    @property
    def fused_over_best(self) -> float:
        """``fused_mse_paired / best_drone_mse``: the fused track against its best input on the
        steps that input exists (the acceptance asks <= 0.9 with >= 2 drones)."""
        return self.fused_mse_paired / self.best_drone_mse

    @property
    def oracle_over_best(self) -> float:
        """``oracle_mse_paired / best_drone_mse``: the fixed-weights oracle against the best
        drone on the same steps (<= 1; 1 when only the best drone predicted the target)."""
        return self.oracle_mse_paired / self.best_drone_mse


def oracle_weighting_mse(errors: np.ndarray, seen: np.ndarray, best: int) -> float:
    """MSE (m^2) of the best fixed weighting of the drones' predictions of one target, over
    the steps drone ``best`` predicted it.

    ``errors`` ``(K, M, 2)`` m: each drone's prediction minus the truth (anything where
    ``seen`` ``(K, M)`` is False). The steps are grouped by which drones predicted the target;
    in a group of drones ``D`` with error Gram matrix ``G_ab = sum_k e_a(k) . e_b(k)`` the
    weights ``w`` (``sum w = 1``, so an unbiased combination stays unbiased) that minimise the
    summed squared error ``w^T G w`` are ``G^-1 1 / (1^T G^-1 1)``, and the minimum is
    ``1 / (1^T G^-1 1)``. Fitted to the truth on the same steps it is scored on, it is an
    optimistic reference: no fusion that weights the same predictions by fixed weights per
    group does better. It is at most the best drone's own MSE, whose weights ``e_best`` are
    one of the candidates, and lower the less the drones' errors are correlated.
    """
    steps = seen[:, best]
    if not steps.any():
        return float("nan")
    groups = seen[steps]  # (S, M): which drones predicted at each of the best drone's steps
    total = 0.0
    for pattern in np.unique(groups, axis=0):
        rows = np.nonzero(steps)[0][(groups == pattern).all(axis=1)]
        e = errors[rows][:, pattern]  # (S_g, D, 2)
        gram = np.einsum("kax,kbx->ab", e, e)
        ones = np.ones(len(gram))
        total += 1.0 / float(ones @ np.linalg.pinv(gram) @ ones)
    return total / int(steps.sum())


#: Taps of :func:`temporal_oracle`: each drone's predictions of the last 2 s (0.2 s steps).
TEMPORAL_TAPS = 10


@dataclass(frozen=True)
class TemporalOracle:
    """:func:`temporal_oracle`'s figures for one target: ``ratio`` its MSE over the best
    drone's on the ``steps`` where every lag exists; ``overall`` the same over all the best
    drone's steps, the fixed-weights oracle (:func:`oracle_weighting_mse`) on the others."""

    ratio: float
    steps: int
    overall: float


def temporal_oracle(
    prediction: np.ndarray, truth: np.ndarray, best: int, taps: int = TEMPORAL_TAPS
) -> TemporalOracle:
    r"""The best linear combination of one target's drones' predictions of the last ``taps``
    steps, fitted to the truth afterwards, against the best drone alone.

    ``prediction`` ``(K, M, 2)`` m: drone ``i``'s prediction at step ``k`` of the position at
    ``k + 1`` (NaN: none); ``truth`` ``(K, 2)`` m: that position; ``best``: the best drone's
    index. Over the drones that predicted the target at all (``D``) and the steps ``k`` where
    each of them predicted it at ``k, k - 1, ..., k - taps + 1``, the estimate

    .. math::
        \hat x_k = \sum_{i \in D} \sum_{l < taps} w_{il} z_i(k - l),\qquad \sum w_{il} = 1

    (one set of weights for both axes, so it stays unbiased and position-invariant) is fitted
    by least squares; ``ratio`` is its MSE over the best drone's on those ``steps``
    (``taps = 1``: the fixed-weights oracle of :func:`oracle_weighting_mse` on those steps),
    ``overall`` over every step the best drone predicted, with the fixed-weights oracle on the
    steps without every lag (an acceptance counts them all). Like that oracle it is an
    optimistic reference, not an estimator: what a linear filter of the same predictions with
    these taps could reach at best. NaN (and 0 steps) when there are fewer than
    ``4 taps |D|`` such steps.
    """
    seen = np.isfinite(prediction).all(axis=-1)  # (K, M)
    drones = np.flatnonzero(seen.any(axis=0)).tolist()
    k = np.arange(taps - 1, len(prediction))
    z_best = prediction[k, best]
    columns = [
        prediction[k - lag, i] - z_best  # sum w = 1: the best drone's now takes the rest
        for i in drones
        for lag in range(taps)
        if (i, lag) != (best, 0)
    ]
    y = truth[k] - z_best
    x = np.stack(columns, axis=-1) if columns else np.zeros((len(k), 2, 0))
    ok = np.isfinite(x).all(axis=(1, 2)) & np.isfinite(y).all(axis=1)
    steps = int(ok.sum())
    if steps < 4 * taps * len(drones):
        return TemporalOracle(float("nan"), 0, float("nan"))
    x, y = x[ok].reshape(-1, x.shape[-1]), y[ok].reshape(-1)
    residual = y - x @ np.linalg.lstsq(x, y, rcond=None)[0] if x.shape[1] else y
    fitted = float((residual**2).sum())
    # The best drone's other steps: the fixed weighting of whichever drones predicted there.
    rest = seen[:, best].copy()
    rest[k[ok]] = False
    errors = prediction - truth[:, None]
    own = float((errors[seen[:, best], best] ** 2).sum())
    fixed = oracle_weighting_mse(errors, seen & rest[:, None], best) * int(rest.sum())
    return TemporalOracle(
        float(fitted / (y**2).sum()), steps, (fitted + (fixed if rest.any() else 0.0)) / own
    )


def fit_temporal_kernel(episodes: Sequence[Episode], taps: int) -> tuple[float, ...]:
    r"""The kernel of :attr:`~dronefl.tracking.FusionConfig.temporal_kernel` that fits
    ``episodes`` best: weights ``w_0, ..., w_{taps-1}`` summing to 1 that minimise

    .. math::
        \sum_{k, j} \lVert x_j(k + 1) - \sum_l w_l \bar z_j(k - l) \rVert^2

    over every step ``k`` and target ``j`` where some drone sent ``j`` at each of ``k, ...,
    k - taps + 1``; ``\bar z_j`` is the plain mean of those drones' sent predictions
    (:func:`sent_predictions`), ``x_j`` the truth (the episodes are where it is known, e.g.
    the crop-field pretraining's). ``ValueError`` when fewer than ``100 taps`` such steps
    exist or ``taps < 1``."""
    if taps < 1:
        raise ValueError(f"taps: must be >= 1, got {taps}")
    x, y = [], []
    for episode in episodes:
        z = sent_predictions(episode)  # (K, M, N, 2)
        truth = episode.target_position[1:]
        seen = np.isfinite(z).all(axis=-1)  # (K, M, N)
        for k in range(taps - 1, len(z)):
            full = seen[k - taps + 1 : k + 1].all(axis=0)  # (M, N)
            for j in full.any(axis=0).nonzero()[0]:
                lagged = z[k - np.arange(taps)][:, full[:, j], j].mean(axis=1)  # (taps, 2)
                x.append((lagged[1:] - lagged[:1]).T)  # sum w = 1: w_0 takes the rest
                y.append(truth[k, j] - lagged[0])
    if len(y) < 100 * taps:
        raise ValueError(f"fit_temporal_kernel: {len(y)} steps with {taps} lags, too few")
    rest = np.linalg.lstsq(np.concatenate(x), np.concatenate(y), rcond=None)[0]
    return (1.0 - float(rest.sum()), *(float(w) for w in rest))


#: How the fused-track cells are split by the number of drones that predicted the target at
#: the step before: two or more, exactly one, none (the track coasts).
VIEWS: tuple[str, ...] = ("2+", "1", "0")


@dataclass(frozen=True)
class ViewsError:
    """The fused track's cells (target, step) of one :data:`VIEWS` group: their mean squared
    error ``mse`` (m^2), how many there are (``cells``) and their ``share`` of the episode's
    summed squared error (so ``share`` over the groups adds up to 1)."""

    mse: float
    cells: int
    share: float


def views_errors(fused: np.ndarray, truth: np.ndarray, seen: np.ndarray) -> dict[str, ViewsError]:
    """Split the fused track's squared error by views: ``fused`` and ``truth`` ``(K+1, N, 2)``
    m, ``seen`` ``(K, M, N)`` whether drone i predicted target j at step k (the track at k + 1
    fuses those predictions)."""
    error = ((fused[1:] - truth[1:]) ** 2).sum(axis=-1)  # (K, N); NaN where no track
    tracked = np.isfinite(error)
    total = float(error[tracked].sum())
    views = seen.sum(axis=1)
    groups = {"2+": views >= 2, "1": views == 1, "0": views == 0}
    out = {}
    for name in VIEWS:
        cells = error[tracked & groups[name]]
        out[name] = ViewsError(
            float(cells.mean()) if cells.size else float("nan"),
            int(cells.size),
            float(cells.sum()) / total if total > 0 else float("nan"),
        )
    return out


@dataclass(frozen=True)
class ReplayResult:
    """A replay of one episode: ``fusion`` (the settings), ``labels`` / ``max_std`` (m) the label
    source and its drop threshold, per-target results, and the whole episode's ``fused_mse`` /
    ``label_mse`` (m^2, mean over cells), ``measurements`` fused or gated, ``rejections``
    (gated out) and ``resets``; ``by_views``: the fused track split by how many drones
    predicted the target at the step before (:data:`VIEWS`; ``"0"`` is coasting on the motion
    model alone), each :class:`ViewsError`; ``correct_bias``: the drones' predictions were
    bias-corrected before the fusion; ``detected_only``: only the predictions made while the
    drone detected the target were fused. The fused tracks and the gating counts are the
    planner's filter's (``fusion.tracks``), the labels the fusion filter's."""

    episode: str
    scenario: str
    fusion: CloudFusion
    labels: str
    max_std: float
    targets: tuple[TargetReplay, ...]
    fused_mse: float
    label_mse: float
    label_kept: float
    measurements: int
    rejections: int
    resets: int
    by_views: dict[str, ViewsError]
    correct_bias: bool = False
    detected_only: bool = False

    @property
    def gated_fraction(self) -> float:
        """Fraction of the measurements that the gate rejected."""
        return self.rejections / max(self.measurements, 1)


def episode_records(episode: Episode) -> list[OnboardRecord]:
    """The drones' onboard records (boxes, detected flags and odometry per step) from the
    episode's checkpoint (:class:`EpisodeError` naming it when it is missing, unreadable or
    shorter than the episode)."""
    path = episode.path / CHECKPOINT_NAME
    if not path.is_file():
        raise EpisodeError(f"{path}: not found (it holds the drones' onboard records)")
    try:
        saved = read_loop_checkpoint(path).records
    except CheckpointError as exc:
        raise EpisodeError(str(exc)) from None
    scenario = episode.scenario
    if len(saved) != len(scenario.drones):
        raise EpisodeError(f"{path}: holds {len(saved)} records, the scenario has drones "
                           f"{', '.join(map(str, scenario.drone_ids))}")  # fmt: skip
    records = []
    for drone, state in zip(scenario.drones, saved, strict=True):
        steps = int(state["steps"])
        if steps < len(episode.prediction):
            raise EpisodeError(f"{path}: its records are shorter than episode.npz")
        record = OnboardRecord(drone.id, drone.altitude, scenario.target_ids, drone.targets,
                               steps, {})  # fmt: skip
        try:
            record.restore(state)
        except (ValueError, KeyError, TypeError) as exc:
            raise EpisodeError(f"{path}: not the records of {scenario.name} ({exc})") from None
        records.append(record)
    return records


def withhold_undetected(episode: Episode, records: list | None = None) -> Episode:
    """``episode`` with only the predictions made while the drone detected the target marked
    sent, as a drone with ``drone.detected_only`` sends them (from ``records``, default: those in
    checkpoint, :func:`episode_records`)."""
    steps = len(episode.prediction)
    records = episode_records(episode) if records is None else records
    detected = np.stack([r.detected[:steps] for r in records], axis=1)
    return replace(episode, sent=episode.sent & detected)


def drone_reports(
    episode: Episode, correct_bias: bool = False, records: list | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The predictions each drone would have sent, ``(K, M, N, 2)`` m (less its bias estimate
    with ``correct_bias``; NaN where it sent none), and the noise it would have sent with each
    (:mod:`dronefl.tracking.reports`), ``(K, M, N, 2, 2)`` m², from the onboard records (boxes
    and odometry) in the episode's checkpoint; box centres are back-projected onto the plane
    at half the vehicle's height; ``records`` as :func:`withhold_undetected`'s."""
    camera, ground_z = ground_plane(episode.scenario)
    records = episode_records(episode) if records is None else records
    detected = [
        record_ground_positions(camera, record, ground_z, slice(0, record.steps))
        for record in records
    ]
    return forecast_residual_reports(sent_predictions(episode), detected, correct_bias=correct_bias)


def sent_predictions(episode: Episode) -> np.ndarray:
    """The predictions that reached the cloud, ``(K, M, N, 2)`` m (NaN where none did)."""
    return received_predictions(episode.prediction, episode.sent)


def replay_setting(
    episode: Episode, setting: Setting, max_std: float = DEFAULT_MAX_STD
) -> ReplayResult:
    """Replay ``episode`` as the cloud of ``setting`` would have fused it: its filters
    (:func:`~dronefl.tracking.fusion.cloud_fusion`), its labels, and the drones sending what
    its ``[drone]`` sub-config says (rebuilt from their records where the episode was flown
    otherwise). An episode flown with the bias correction cannot be replayed without it
    (:class:`EpisodeError`): only the corrected predictions were sent."""
    drone = setting.drone
    if episode.bias_corrected and not drone.correct_bias:
        raise EpisodeError(
            f"{episode.path}: its drones corrected their predictions in flight; replay it with "
            "drone.correct_bias = true (--set drone.correct_bias=true)"
        )
    filters = cloud_fusion(setting.fusion, drone.noise_reports, episode.scenario)
    return replay(
        episode,
        filters,
        labels=setting.learning.labels,
        max_std=max_std,
        correct_bias=drone.correct_bias and not episode.bias_corrected,
        detected_only=drone.detected_only and not episode.withheld,
    )


def replay(
    episode: Episode,
    filters: CloudFusion,
    labels: str = "smoothed",
    max_std: float = DEFAULT_MAX_STD,
    correct_bias: bool = False,
    detected_only: bool = False,
) -> ReplayResult:
    """Re-fuse ``episode``'s predictions with the cloud's ``filters`` and make its ``labels``;
    with ``correct_bias`` the drones' predictions are first corrected as in flight
    (:meth:`~dronefl.tracking.reports.NoiseReporter.correct`); with ``detected_only`` only
    the predictions made while the drone detected the target are fused
    (:func:`withhold_undetected`); with ``filters.fusion.noise_split = "reported"`` the
    drones' reports are rebuilt from their records (a deployed episode's: as received). The
    fused tracks are the planner's filter's, the labels the fusion filter's, as the closed loop
    flies them. Each drone's MSE is that of the predictions fused."""
    scenario = episode.scenario
    config = filters.fusion
    if correct_bias and episode.bias_corrected:
        raise EpisodeError(
            f"{episode.path}: its predictions were corrected in flight already; replay it "
            "without correcting them again"
        )
    rebuilt = config.noise_split == "reported" or correct_bias  # from the drones' records
    reports = None
    if episode.received_reports is not None:  # deployed: as received, nothing to rebuild
        if correct_bias:
            raise EpisodeError(
                f"{episode.path}: a deployed episode holds what the cloud received (the "
                "drones' records stay on the drones); replay it with the correction it flew"
            )
        if config.noise_split == "reported":
            reports = episode.received_reports
        rebuilt = detected_only = False
    records = episode_records(episode) if detected_only or rebuilt else None  # read once
    if detected_only:
        episode = withhold_undetected(episode, records)
    if rebuilt:
        sent, reports = drone_reports(episode, correct_bias, records)
        episode = replace(episode, prediction=sent)
        if config.noise_split != "reported":
            reports = None
    else:
        episode = replace(episode, prediction=sent_predictions(episode))
    fuser = Fuser(scenario.target_ids, scenario.drone_ids, filters.tracks)
    label_fuser = (
        None
        if filters.planner is None
        else Fuser(scenario.target_ids, scenario.drone_ids, filters.fusion)
    )
    n_steps = episode.prediction.shape[0]
    fused = np.full_like(episode.track_position, np.nan)
    seen = np.isfinite(episode.prediction).all(axis=-1)  # (K, M, N)
    drone_ids, target_ids = scenario.drone_ids, scenario.target_ids
    for k in range(n_steps):
        measurements = [
            PositionMeasurement(
                drone_ids[i],
                target_ids[j],
                episode.prediction[k, i, j],
                None if reports is None or np.isnan(reports[k, i, j]).any() else reports[k, i, j],
            )
            for i, j in zip(*np.nonzero(seen[k]), strict=True)
        ]
        tracks, _ = update_filters(fuser, label_fuser, float(episode.t[k + 1]), measurements)
        for target_id, track in tracks.items():
            fused[k + 1, target_ids.index(target_id)] = track.position
    labelled = fuser if label_fuser is None else label_fuser
    made = make_labels(labels, labelled, episode.t, episode.target_position, max_std)
    truth = episode.target_position
    targets = []
    for j, target_id in enumerate(scenario.target_ids):
        drones, best, best_i, paired, oracle = [], np.inf, 0, float("nan"), float("nan")
        errors = episode.prediction[:, :, j] - truth[1:, None, j]  # (K, M, 2)
        for i, drone_id in enumerate(scenario.drone_ids):
            ok = seen[:, i, j]
            if ok.any():
                mse = float((errors[ok, i] ** 2).sum(-1).mean())
                drones.append(DroneError(drone_id, mse, int(ok.sum())))
                if mse < best:  # the fused track at k + 1 on the steps k this drone predicted
                    best, best_i, paired = mse, i, _mse(fused[1:][ok, j], truth[1:][ok, j])
        temporal = TemporalOracle(float("nan"), 0, float("nan"))
        if drones:
            oracle = oracle_weighting_mse(errors, seen[:, :, j], best_i)
            temporal = temporal_oracle(episode.prediction[:, :, j], truth[1:, j], best_i)
        targets.append(
            TargetReplay(
                target_id,
                tuple(drones),
                _mse(fused[:, j], truth[:, j]),
                paired,
                _mse(made.position[:, j], truth[:, j]),
                float(np.isfinite(made.position[:, j, 0]).mean()),
                _mse(episode.track_position[:, j], truth[:, j]),
                oracle,
                temporal.ratio,
                temporal.steps,
                temporal.overall,
            )
        )
    return ReplayResult(
        str(episode.path),
        scenario.name,
        filters,
        labels,
        max_std,
        tuple(targets),
        _mse(fused, truth),
        _mse(made.position, truth),
        made.kept,
        fuser.measurements,
        fuser.rejections,
        fuser.resets,
        views_errors(fused, truth, seen),
        correct_bias,
        detected_only,
    )


def _mse(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Mean squared position error (m^2) over the cells where ``estimate`` is finite."""
    ok = np.isfinite(estimate).all(axis=-1)
    if not ok.any():
        return float("nan")
    return float(((estimate[ok] - truth[ok]) ** 2).sum(axis=-1).mean())


def result_dict(result: ReplayResult) -> dict:
    """The JSON form of ``result`` (every field, plus the derived ratios)."""
    out = asdict(result)
    out["gated_fraction"] = result.gated_fraction
    for entry, target in zip(out["targets"], result.targets, strict=True):
        entry["best_drone_mse"] = target.best_drone_mse
        entry["fused_over_best"] = target.fused_over_best
        entry["oracle_over_best"] = target.oracle_over_best
    return out


def format_result(result: ReplayResult) -> str:
    """A markdown table: per target, each drone's prediction MSE beside the fused and label MSE."""
    drone_ids = sorted({d.drone_id for t in result.targets for d in t.drones})
    head = ["target", *(f"drone {i}" for i in drone_ids), "best drone", "fused (filtered)"]
    head += ["fused, best's steps", "fused / best", "oracle / best", "temporal oracle / best"]
    head += [f"{result.labels} label", "label kept"]
    head += ["as flown"]
    fusion = result.fusion.fusion
    planner = result.fusion.planner
    lines = [
        f"Replay of {result.episode} ({result.scenario}), fusion method "
        f"{fusion.method!r}, q = {fusion.acceleration_psd} m²/s³"
        + (
            f" (the fused tracks: a second filter with q = {planner.acceleration_psd})"
            if planner is not None
            else ""
        )
        + (", the drones' predictions bias-corrected" if result.correct_bias else "")
        + (", only those made while the drone detected the target" if result.detected_only else "")
        + (
            f", the fused tracks' output a {len(fusion.temporal_kernel)}-tap temporal kernel"
            if fusion.temporal_kernel is not None
            else ""
        )
        + "; MSE in m².",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for t in result.targets:
        by_drone = {d.drone_id: f"{d.mse:.2f} (n={d.n})" for d in t.drones}
        row = [str(t.target_id), *(by_drone.get(i, "—") for i in drone_ids)]
        row += [f"{t.best_drone_mse:.2f}", f"{t.fused_mse:.2f}", f"{t.fused_mse_paired:.2f}"]
        row += [f"{t.fused_over_best:.2f}x", f"{t.oracle_over_best:.2f}x"]
        row += [
            f"{t.temporal_oracle_over_best:.2f}x on {t.temporal_oracle_steps} steps, "
            f"{t.temporal_oracle_overall:.2f}x on all"
            if t.temporal_oracle_steps
            else "—"
        ]
        row += [f"{t.label_mse:.2f}", f"{100 * t.label_kept:.0f} %", f"{t.recorded_mse:.2f}"]
        lines.append("| " + " | ".join(row) + " |")
    lines += [
        "",
        f"All targets: fused {result.fused_mse:.2f} m², {result.labels} labels "
        f"{result.label_mse:.2f} m² ({100 * result.label_kept:.0f} % kept, max std "
        f"{result.max_std} m); gated out {result.rejections} of {result.measurements} "
        f"measurements ({100 * result.gated_fraction:.1f} %), {result.resets} track resets.",
        "Fused track by the drones that saw the target the step before: "
        + "; ".join(
            f"{name}: {v.mse:.2f} m² ({v.cells} cells, {100 * v.share:.0f} % of the error)"
            for name, v in result.by_views.items()
        )
        + " (0: coasting).",
        "oracle / best: the best fixed weights of the target's drones' predictions, fitted to "
        "the truth afterwards, on the best drone's steps (no fixed-weight fusion of these "
        "predictions does better). temporal oracle / best: the same for the best linear "
        f"combination of their last {TEMPORAL_TAPS} predictions each (weights summing to 1), "
        "on the steps where all of them exist, and on all the best drone's steps with the "
        "fixed weights on the others.",
    ]
    return "\n".join(lines)


def write_result(result: ReplayResult, out: str | Path) -> Path:
    """Write ``replay.json`` and ``replay.md`` into ``out``; returns the folder."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "replay.json", result_dict(result))
    atomic_write_text(out / "replay.md", format_result(result) + "\n")
    return out
