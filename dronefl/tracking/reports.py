"""Each drone's own estimate of its prediction noise, from its next detection.

A drone predicts at step ``k`` where each of its targets will be at ``k + 1``. At ``k + 1`` it
detects the target again and back-projects the box centre onto the ground, which gives it a
measurement ``g`` of where the target is that needs no model. Its forecast residual
``e = z_k - g_{k+1}`` has second moment

.. math::
    E[e e^T] = R_{pred} + R_{proj}

(for errors independent of each other): the prediction error it wants plus the projection
error of one box (0.03-0.17 m² in Case 3, growing with the altitude as the prediction error
does). It exists only while the target is detected, so where targets leave the view (Case 2)
it misses the largest errors. :class:`ForecastResidual` keeps an
EMA of ``e e^T`` per target, the *reported noise* the drone can send with its predictions.

The same residual's first moment is the prediction's *bias* plus the projection's, and the
latter is small (|mean| <= 0.05 m on Case 3's tuning episodes, where the fixed models'
predictions are off by 0.1-1.3 m on average, constant over the episode). With
``correct_bias`` a drone subtracts its running estimate ``b`` of that mean from what it sends,
``z'_k = z_k - b``, and updates ``b <- b + rate (z'_k - g_{k+1})``: an EMA of the raw residual
``z_k - g_{k+1}`` that starts at zero, written as an integrator of what was sent. A new model
(an FL round) has another bias: the drone then re-estimates ``b`` as that EMA of the new
model's residuals over the last :data:`REBASE_STEPS` steps of its record, as if it had flown
it (:meth:`NoiseReporter.rebase`).

The cloud cannot get this split from the predictions alone: with two drones on a target the
residual between them measures only ``R_1 + R_2`` (the adaptive estimate gives both the same
share). The reports give the ratio (on Case 3's tuning episodes they rank the high drone above
the low one on every target), the fusion's adaptive ``R`` the scale
(:attr:`~dronefl.tracking.FusionConfig.noise_split`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from dronefl.sim.camera import PinholeCamera

if TYPE_CHECKING:
    from dronefl.config import Scenario
    from dronefl.models.online import OnboardRecord
    from dronefl.models.predictor import TrajectoryPredictor

#: EMA rate per detected step of the reported noise (the fusion's adaptation rate).
REPORT_RATE = 0.02
#: Steps of its record over which a drone re-estimates its bias after a model update: the
#: EMA's weight beyond them is below e^-5.
REBASE_STEPS = int(np.ceil(5 / REPORT_RATE))


def box_ground_positions(
    camera: PinholeCamera,
    boxes: np.ndarray,
    odometry: np.ndarray,
    ground_z: float,
) -> np.ndarray:
    """Back-project the centres of ``boxes`` ``(..., n, 4)`` (normalised ``cx, cy, w, h``)
    seen from the drone at ``odometry`` ``(..., 12)`` onto the plane ``z = ground_z`` m;
    returns world positions ``(..., n, 2)`` m (NaN where a box is NaN)."""
    boxes = np.asarray(boxes, dtype=float)
    odometry = np.asarray(odometry, dtype=float)
    out = np.full((*boxes.shape[:-1], 2), np.nan)
    for index in np.ndindex(boxes.shape[:-2]):
        pose = odometry[index]
        out[index] = camera.ground_point(boxes[index][:, :2], pose[:3], float(pose[8]), ground_z)
    return out


def ground_plane(scenario: Scenario) -> tuple[PinholeCamera, float]:
    """The drones' camera and the height (m) onto which they back-project box centres: half
    the vehicle's height."""
    return PinholeCamera.from_spec(scenario.camera), scenario.vehicle.height / 2


def record_ground_positions(
    camera: PinholeCamera, record: OnboardRecord, ground_z: float, rows: int | slice
) -> np.ndarray:
    """The detections of an onboard record's ``rows`` back-projected onto the plane
    ``z = ground_z`` m (:func:`box_ground_positions`), ``(..., n, 2)`` m, NaN where a target
    was not detected."""
    boxes = np.where(record.detected[rows, ..., None], record.boxes[rows], np.nan)
    return box_ground_positions(camera, boxes, record.odometry[rows], ground_z)


def detected_now(record: OnboardRecord) -> np.ndarray:
    """Whether the drone detects each of its assigned targets at the record's last step,
    ``(n_assigned,)`` bool in ``record.assigned`` order: with ``detected_only`` a drone sends
    only those targets' predictions. A prediction made while the target is not in the image
    (occluded, or at the edge of the view) comes from a window with gaps, and its error is
    ~35x larger (Case 2, orchard, docs/fusion.md, "The drones send what they see")."""
    return np.asarray(record.detected[record.steps - 1, record.assigned], dtype=bool)


class ForecastResidual:
    """One drone's running estimate of each target's prediction noise, ``(n, 2, 2)`` m².

    Call :meth:`observe` once per step with the ground positions of this step's detections
    (NaN where the target was not detected), then :meth:`predicted` with this step's
    predictions (a step without any: skip it). The residual of the previous step's prediction
    against this step's detection updates ``S_j <- (1 - rate) S_j + rate e e^T`` (the first
    sample is taken as it is) and the bias ``b_j <- b_j + rate e`` (from zero); a target
    without both keeps its estimates. :meth:`noise` is NaN for a target that has had no
    residual yet; :meth:`bias` is zero then.
    """

    def __init__(self, n_targets: int, rate: float = REPORT_RATE) -> None:
        if not 0 < rate <= 1:
            raise ValueError(f"rate: must be in (0, 1], got {rate}")
        self.rate = rate
        self._s = np.full((n_targets, 2, 2), np.nan)
        self._b = np.zeros((n_targets, 2))
        self._last = np.full((n_targets, 2), np.nan)

    def observe(self, detected: np.ndarray) -> None:
        """Update from this step's detected ground positions ``(n, 2)`` m."""
        detected = np.asarray(detected, dtype=float)
        e = self._last - detected
        ok = np.isfinite(e).all(axis=1)
        self._s[ok] = _ema(self._s[ok], e[ok, :, None] * e[ok, None, :], self.rate)
        self._b[ok] += self.rate * e[ok]
        self._last[:] = np.nan  # a prediction is compared with the next step's detection only

    def predicted(self, positions: np.ndarray) -> None:
        """Remember this step's predictions ``(n, 2)`` m (NaN: none) for the next residual."""
        self._last = np.array(positions, dtype=float)

    def noise(self) -> np.ndarray:
        """The reported noise of every target, ``E[e e^T]`` ``(n, 2, 2)`` m² (a copy)."""
        return self._s.copy()

    def rebase_bias(self, raw: np.ndarray, detected: np.ndarray) -> None:
        """Re-estimate the bias from zero as the EMA of ``raw[k] - detected[k + 1]``: ``raw``
        ``(L, n, 2)`` m, a new model's predictions on recorded steps, ``detected``
        ``(L + 1, n, 2)`` m the detections of those steps and the next (NaN: none). The noise
        and the prediction awaiting its residual are kept."""
        b = np.zeros_like(self._b)
        for e in np.asarray(raw, dtype=float) - np.asarray(detected, dtype=float)[1:]:
            ok = np.isfinite(e).all(axis=1)
            b[ok] += self.rate * (e[ok] - b[ok])
        self._b = b

    def bias(self) -> np.ndarray:
        """The running mean of every target's residual of the raw predictions, ``(n, 2)`` m
        (a copy): what ``correct_bias`` subtracts."""
        return self._b.copy()


class NoiseReporter:
    """What a drone runs to report its noise and correct its bias, fed from its onboard
    record (:class:`~dronefl.roles.DroneNode`, in the closed loop and in a deployed drone).

    Each step: :meth:`observe` once the step's detections are in the record, then
    :meth:`correct` the predictions (with ``correct_bias``), then :meth:`report` (or, without
    reports, :meth:`remember`) with the predictions it sends (the positions as they travel).
    """

    def __init__(self, scenario: Scenario, rate: float = REPORT_RATE) -> None:
        self.camera, self.ground_z = ground_plane(scenario)
        self.column = {int(t): j for j, t in enumerate(scenario.target_ids)}
        self.residual = ForecastResidual(len(self.column), rate)

    def state(self) -> dict:
        """The running noise, bias and awaiting prediction (arrays), for a checkpoint."""
        r = self.residual
        return {"noise": r._s.copy(), "bias": r._b.copy(), "last": r._last.copy()}

    def restore(self, state: dict) -> None:
        """Continue from ``state`` (:meth:`state` of a reporter of the same scenario)."""
        r = self.residual
        r._s, r._b, r._last = state["noise"].copy(), state["bias"].copy(), state["last"].copy()

    def observe(self, record: OnboardRecord) -> None:
        """Compare the last predictions with the detections ``record`` has just stored."""
        ground = record_ground_positions(self.camera, record, self.ground_z, record.steps - 1)
        self.residual.observe(ground)

    def correct(self, target_ids: Sequence[int], positions: np.ndarray) -> np.ndarray:
        """The predictions ``positions`` ``(n, 2)`` m of ``target_ids`` less each target's
        bias estimate (:meth:`ForecastResidual.bias`; zero before its first residual)."""
        bias = self.residual.bias()
        return np.asarray(positions, dtype=float) - bias[[self.column[t] for t in target_ids]]

    def rebase(
        self,
        record: OnboardRecord,
        predictor: TrajectoryPredictor,
        past_steps: int,
        detected_only: bool = False,
    ) -> None:
        """After a model update: re-estimate the bias with ``predictor`` (the new model, L_p =
        ``past_steps``) over the last :data:`REBASE_STEPS` residuals ``record`` holds
        (:meth:`ForecastResidual.rebase_bias`); with ``detected_only`` from the predictions
        of the steps that detected their target only (those a drone with ``detected_only``
        sends, whose residuals it keeps in flight)."""
        last = record.steps - 1  # the step whose prediction awaits its residual
        first = max(past_steps - 1, last - REBASE_STEPS)
        if first >= last:
            return
        raw = np.full((last - first, len(self.column), 2), np.nan)
        for row, k in enumerate(range(first, last)):
            window = slice(k + 1 - past_steps, k + 1)
            raw[row, record.assigned] = predictor.predict(
                record.odometry[window],
                record.boxes[window][:, record.assigned],
                record.detected[window][:, record.assigned],
            )[:, 0]
        if detected_only:
            raw[~record.detected[first:last]] = np.nan
        ground = record_ground_positions(self.camera, record, self.ground_z, slice(first, last + 1))
        self.residual.rebase_bias(raw, ground)

    def report(
        self, target_ids: Sequence[int], positions: np.ndarray
    ) -> tuple[tuple[int, ...], np.ndarray]:
        """The noise to send with the predictions ``positions`` ``(n, 2)`` m of
        ``target_ids``: the targets that have an estimate and their ``(n', 2, 2)`` m²
        (residuals of the earlier predictions only); keeps the predictions for the next
        residual (:meth:`remember`)."""
        noise = self.residual.noise()
        self.remember(target_ids, positions)
        known = tuple(t for t in target_ids if np.isfinite(noise[self.column[t]]).all())
        return known, noise[[self.column[t] for t in known]].reshape(-1, 2, 2)

    def remember(self, target_ids: Sequence[int], positions: np.ndarray) -> None:
        """Keep the predictions ``positions`` ``(n, 2)`` m of ``target_ids`` as sent, for the
        next step's residual (what a drone that corrects but does not report calls instead of
        :meth:`report`)."""
        predicted = np.full((len(self.column), 2), np.nan)
        for target_id, position in zip(target_ids, positions, strict=True):
            predicted[self.column[target_id]] = position
        self.residual.predicted(predicted)


def forecast_residual_reports(
    predictions: np.ndarray,
    detected: Sequence[np.ndarray],
    rate: float = REPORT_RATE,
    correct_bias: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """The predictions every drone would have sent in an episode and the noise it would have
    reported with each.

    ``predictions`` ``(K, M, N, 2)``: the raw prediction made at step ``k`` for ``k + 1``
    (NaN: none); ``detected[i]`` ``(>= K, N, 2)``: drone ``i``'s back-projected detections per
    step. Returns the predictions as sent ``(K, M, N, 2)`` (less the bias estimate with
    ``correct_bias``, else the input) and ``(K, M, N, 2, 2)``: the report sent with prediction
    ``k``, built from the residuals of predictions ``0 .. k - 1`` (causal: what the drone knew
    when it sent it).
    """
    n_steps, n_drones, n_targets, _ = predictions.shape
    sent = np.array(predictions, dtype=float)
    reports = np.full((n_steps, n_drones, n_targets, 2, 2), np.nan)
    for i in range(n_drones):
        residual = ForecastResidual(n_targets, rate)
        for k in range(n_steps):
            residual.observe(detected[i][k])
            reports[k, i] = residual.noise()
            if correct_bias:
                sent[k, i] -= residual.bias()
            residual.predicted(sent[k, i])
    return sent, reports


def _ema(old: np.ndarray, sample: np.ndarray, rate: float) -> np.ndarray:
    """``(1 - rate) old + rate sample``, or ``sample`` where ``old`` is NaN (the first)."""
    return np.where(np.isnan(old), sample, (1 - rate) * old + rate * sample)
