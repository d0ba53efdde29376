"""Pseudo-labels for federated training, made in the cloud from the fused tracks (SPEC §8).

At an FL round the cloud has the whole past: :class:`SmoothedLabels` (the default) runs the RTS
smoother (:meth:`~dronefl.tracking.fusion.Fuser.smooth`) over the fused history, so the label of
time ``t`` also uses the predictions made after ``t``; :class:`FilteredLabels` gives the filtered
tracks (the paper's labels) and :class:`GroundTruthLabels` the simulator's truth (the ablation).
A label whose position std exceeds ``max_std`` (a target nobody saw for a while) is dropped
(NaN), so the windows built on it are not trained on. One class per source, registered in
:data:`LABEL_SOURCES`. :func:`label_drones` says which drone learns from which label.

Use at round time, with the episode's time grid ``t`` ``(T,)`` (index ``k`` = time ``k dt``)::

    labels = make_labels("smoothed", fuser, t[:steps], truth=None)
    labels.position  # (steps, N, 2) m, NaN where dropped, in fuser.target_ids order
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from dronefl.settings import LABEL_DRONES
from dronefl.tracking.fusion import Fuser

#: Default largest label std (m, per axis, rms over x and y) kept for training.
DEFAULT_MAX_STD = 1.5


@dataclass(frozen=True)
class Labels:
    """Training labels on a time grid.

    ``t`` ``(T,)`` s; ``target_ids`` ``(N,)``; ``position`` ``(T, N, 2)`` m, NaN where there is
    no label (no track yet, or dropped as too uncertain); ``variance`` ``(T, N)`` m^2, the
    label's per-axis variance ``Tr P_pos / 2`` (0 for ground truth, NaN where no label);
    ``source``: the name in :data:`LABEL_SOURCES`.
    """

    source: str
    t: np.ndarray
    target_ids: np.ndarray
    position: np.ndarray
    variance: np.ndarray

    @property
    def kept(self) -> float:
        """Fraction of (time, target) cells with a label."""
        return float(np.isfinite(self.position[..., 0]).mean())


class LabelSource(ABC):
    """Makes :class:`Labels` from the fusion's state at round time.

    ``max_std`` (m): labels whose per-axis std exceeds it are dropped (not for ground truth).
    """

    name: str

    def __init__(self, max_std: float = DEFAULT_MAX_STD) -> None:
        if not (math.isfinite(max_std) and max_std > 0):
            raise ValueError(f"max_std: must be a positive number of metres, got {max_std}")
        self.max_std = float(max_std)

    @abstractmethod
    def labels(self, fuser: Fuser, t: np.ndarray, truth: np.ndarray | None) -> Labels:
        """Labels on grid ``t`` ``(T,)`` s for ``fuser``'s targets; ``truth`` ``(T, N, 2)`` m
        (needed by ground truth only)."""

    def _from_tracks(self, fuser: Fuser, t: np.ndarray, tracks: dict) -> Labels:
        """Place per-target ``(times (S,), positions (S, 2), covariances (S, 2, 2))`` on ``t``,
        dropping labels above ``max_std``."""
        t = np.asarray(t, dtype=float)
        n = len(fuser.target_ids)
        position = np.full((len(t), n, 2), np.nan)
        variance = np.full((len(t), n), np.nan)
        for j, target_id in enumerate(fuser.target_ids):
            if target_id not in tracks:
                continue
            times, pos, cov = tracks[target_id]
            index = np.clip(np.searchsorted(t, times - 1e-6), 0, max(len(t) - 1, 0))
            on_grid = (np.abs(t[index] - times) < 1e-6) if len(t) else np.zeros(0, bool)
            var = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
            keep = on_grid & (var <= self.max_std**2)
            position[index[keep], j] = pos[keep]
            variance[index[keep], j] = var[keep]
        return Labels(self.name, t, np.array(fuser.target_ids), position, variance)


class SmoothedLabels(LabelSource):
    """RTS-smoothed fused tracks (:func:`~dronefl.tracking.smoother.rts_smooth`)."""

    name = "smoothed"

    def labels(self, fuser: Fuser, t: np.ndarray, truth: np.ndarray | None) -> Labels:
        tracks = {j: (s.t, s.position, s.position_covariance) for j, s in fuser.smooth().items()}
        return self._from_tracks(fuser, t, tracks)


class FilteredLabels(LabelSource):
    """The filtered fused tracks, as the fusion produced them step by step (the paper)."""

    name = "filtered"

    def labels(self, fuser: Fuser, t: np.ndarray, truth: np.ndarray | None) -> Labels:
        tracks = {}
        for j in fuser.target_ids:
            h = fuser.history(j)
            if h is not None:
                tracks[j] = (h.t, h.mean[:, :2], h.covariance[:, :2, :2])
        return self._from_tracks(fuser, t, tracks)


class GroundTruthLabels(LabelSource):
    """The simulator's true positions (an ablation: no field deployment has them)."""

    name = "ground_truth"

    def labels(self, fuser: Fuser, t: np.ndarray, truth: np.ndarray | None) -> Labels:
        t = np.asarray(t, dtype=float)
        shape = (len(t), len(fuser.target_ids), 2)
        if truth is None or np.shape(truth) != shape:
            raise ValueError(f"ground_truth labels need truth of shape {shape}")
        position = np.asarray(truth, dtype=float).copy()
        return Labels(self.name, t, np.array(fuser.target_ids), position, np.zeros(shape[:2]))


def label_drones(
    predicted: np.ndarray,
    rule: str,
    assigned: np.ndarray | None = None,
) -> np.ndarray:
    """Which drone learns from which label under ``rule`` (a name in :data:`LABEL_DRONES`).

    ``predicted`` ``(T, M, N)`` bool: drone ``i``'s prediction of target ``j`` for time step
    ``t`` reached the cloud. With ``assigned`` ``(M, N)`` bool (drone
    ``i`` watches target ``j``), drone ``i``'s own condition is that it watches the target,
    not that its prediction reached the cloud: drones that withhold the predictions of targets
    they do not detect (``drone.detected_only``) still learn those steps from the others' views (a
    drone trains only on windows holding a detection, so a label at a step it had none is not
    used). Returns ``(M, T, N)`` bool: drone ``i`` trains on the label of target ``j`` at step
    ``t``.
    """
    if rule not in LABEL_DRONES:
        raise ValueError(f"label drones: unknown rule {rule!r} ({', '.join(LABEL_DRONES)})")
    predicted = np.asarray(predicted, dtype=bool)
    n_steps, n_drones, n_targets = predicted.shape
    if rule == "all":
        return np.ones((n_drones, n_steps, n_targets), dtype=bool)
    if assigned is not None and np.shape(assigned) != (n_drones, n_targets):
        raise ValueError(
            f"assigned: expected shape ({n_drones}, {n_targets}), got {np.shape(assigned)}"
        )
    watches = None if assigned is None else np.asarray(assigned, dtype=bool)
    out = np.zeros((n_drones, n_steps, n_targets), dtype=bool)
    for i in range(n_drones):
        sources = np.arange(n_drones) != i
        own = predicted[:, i] if watches is None else watches[i]
        out[i] = own & predicted[:, sources].any(axis=1)
    return out


def drone_labels(
    position: np.ndarray,
    prediction: np.ndarray,
    rule: str,
    assigned: np.ndarray | None = None,
) -> np.ndarray:
    """Each drone's training labels ``(M, T, N, 2)`` m under ``rule`` (see :func:`label_drones`,
    also for ``assigned``), NaN where it has none: ``position`` ``(T, N, 2)`` m the labels of
    steps ``0 .. T-1`` (NaN where there is none), ``prediction`` ``(T, M, N, 2)`` m the
    predictions that reached the cloud at each step (NaN where none did; the prediction made
    at step ``t`` is of step ``t + 1``, and so is the label it went into)."""
    position = np.asarray(position, dtype=float)
    prediction = np.asarray(prediction, dtype=float)
    steps = position.shape[0]
    if (
        prediction.ndim != 4
        or prediction.shape[0] < steps
        or prediction.shape[2:] != position.shape[1:]
    ):
        raise ValueError(
            f"prediction: expected (>= {steps}, M, {position.shape[1]}, 2), got {prediction.shape}"
        )
    predicted = np.zeros((steps, *prediction.shape[1:3]), dtype=bool)
    predicted[1:] = np.isfinite(prediction[: steps - 1]).all(axis=-1)
    mask = label_drones(predicted, rule, assigned)
    return np.where(mask[..., None], position[None], np.nan)


#: Label sources by name (``learning.labels``).
LABEL_SOURCES: dict[str, type[LabelSource]] = {
    "smoothed": SmoothedLabels,
    "filtered": FilteredLabels,
    "ground_truth": GroundTruthLabels,
}


def make_labels(
    source: str,
    fuser: Fuser,
    t: np.ndarray,
    truth: np.ndarray | None = None,
    max_std: float = DEFAULT_MAX_STD,
) -> Labels:
    """Labels from source ``source`` (a key of :data:`LABEL_SOURCES`) on grid ``t`` ``(T,)`` s;
    ``truth`` ``(T, N, 2)`` m for ``ground_truth``; ``max_std`` m as in :class:`LabelSource`."""
    if source not in LABEL_SOURCES:
        raise ValueError(f"labels: unknown source {source!r} ({', '.join(LABEL_SOURCES)})")
    return LABEL_SOURCES[source](max_std).labels(fuser, t, truth)
