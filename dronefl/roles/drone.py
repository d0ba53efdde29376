"""The drone's half of the closed loop (paper Fig. 3): detect -> record -> predict -> correct ->
report.

:class:`DroneNode` is the same object in ``dronefl track`` (stepped in one process) and in a
deployed drone process (``dronefl drone``, which feeds it the world's sensors over Zenoh and
publishes its :class:`Uplink`'s payload). Each step it stores the step's odometry and
detections in its onboard record (:meth:`DroneNode.sense`), predicts its assigned targets'
next positions from the last L_p steps (:meth:`DroneNode.forecast`), and makes what it sends
(:meth:`DroneNode.uplink`): with ``drone.correct_bias`` the predictions less its running bias
estimate, with ``drone.detected_only`` only those of the targets it detects at that step,
with ``drone.noise_reports`` its running noise estimate beside them
(:mod:`dronefl.tracking.reports`). The positions are those the radio carries (the wire
format's centimetres), which the residuals of the next step compare.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dronefl.config import DroneSpec, Scenario
from dronefl.models.online import OnboardRecord
from dronefl.models.predictor import TrajectoryPredictor
from dronefl.settings import DroneSetting
from dronefl.tracking.reports import NoiseReporter, detected_now
from dronefl.types import Detection, Odometry
from dronefl.wire import NoiseReportMessage, PredictionMessage


@dataclass(frozen=True)
class Uplink:
    """What drone ``drone_id`` made at step ``step``: every prediction of its assigned targets
    (``target_ids``, ``positions`` ``(n, 2)`` m, as corrected, and as the radio carried them
    where ``sent`` ``(n,)`` is set), the noise it ``reports`` by target id (``(2, 2)`` m²),
    and the ``payload`` its radio carries (the prediction message, then the noise report; empty
    for a drone whose predictions are made in the cloud) of which ``prediction_bytes`` and
    ``report_bytes`` (0 before the drone's first window: it had nothing to predict)."""

    drone_id: int
    step: int
    target_ids: tuple[int, ...] = ()
    positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    sent: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    reports: dict[int, np.ndarray] = field(default_factory=dict)
    payload: bytes = b""
    prediction_bytes: int = 0
    report_bytes: int = 0

    @property
    def sent_ids(self) -> tuple[int, ...]:
        """The targets whose prediction reached the cloud."""
        return tuple(t for t, s in zip(self.target_ids, self.sent, strict=True) if s)


class DroneNode:
    """One drone's onboard side (module doc): its onboard record, its predictor and, with
    reports or the bias correction, its :class:`~dronefl.tracking.reports.NoiseReporter`.

    ``spec`` the drone in ``scenario``; ``setting`` what it sends; ``past_steps`` L_p;
    ``capacity`` steps its record holds; ``meta`` what its record's log says of the run;
    ``predictor`` its on-board model (``None`` for a drone whose predictions the cloud makes
    from its raw inputs: :meth:`uplink` is then given them); ``radio``: whether its
    predictions cross the radio (encoded, counted); off for the centralized baselines, whose
    predictions are made in the cloud.
    """

    def __init__(
        self,
        spec: DroneSpec,
        scenario: Scenario,
        setting: DroneSetting,
        past_steps: int,
        capacity: int,
        meta: dict,
        predictor: TrajectoryPredictor | None,
        radio: bool = True,
    ) -> None:
        self.drone_id = spec.id
        self.setting, self.past_steps, self.radio = setting, past_steps, radio
        self.record = OnboardRecord(
            spec.id, spec.altitude, scenario.target_ids, spec.targets, capacity, meta
        )
        self.predictor = predictor
        wanted = setting.noise_reports or setting.correct_bias
        self.reporter = NoiseReporter(scenario) if wanted else None

    def sense(self, odometry: Odometry, detections: tuple[Detection, ...]) -> None:
        """Store one step's odometry and detections; the residuals of the last predictions
        against these detections update the noise and bias estimates."""
        self.record.append(odometry, detections)
        if self.reporter is not None:
            self.reporter.observe(self.record)

    def forecast(self) -> np.ndarray | None:
        """The on-board model's prediction of every assigned target one step ahead,
        ``(n_assigned, 2)`` m (NaN where it has no detection in its window); ``None`` before
        L_p steps."""
        window = self.record.window(self.past_steps)
        if window is None or self.predictor is None:
            return None
        return self.predictor.predict(*window)[:, 0]

    def uplink(self, step: int, predicted: np.ndarray | None) -> Uplink:
        """What the drone sends at ``step`` given its prediction ``predicted`` of every
        assigned target (``(n_assigned, 2)`` m, :meth:`forecast` or the cloud's; ``None``:
        nothing to predict yet, an empty message)."""
        if predicted is None:
            empty = PredictionMessage(self.drone_id, step, (), np.zeros((0, 1, 2))).encode()
            return Uplink(self.drone_id, step, payload=empty if self.radio else b"")
        record = self.record
        assigned = record.target_ids[record.assigned]
        seen = np.isfinite(predicted).all(axis=1)
        ids, positions = tuple(int(t) for t in assigned[seen]), predicted[seen]
        if self.setting.correct_bias:
            positions = self.reporter.correct(ids, positions)
        send = detected_now(record)[seen] if self.setting.detected_only else np.ones(len(ids), bool)
        sent_ids, sent = tuple(np.array(ids, dtype=int)[send].tolist()), positions[send]
        payload, prediction_bytes = b"", 0
        if self.radio:  # what the cloud and the next residual see is what the radio carried
            payload = PredictionMessage(self.drone_id, step, sent_ids, sent[:, None]).encode()
            prediction_bytes = len(payload)
            received = PredictionMessage.decode(payload)
            sent_ids, sent = received.target_ids, received.positions[:, 0]
        reports: dict[int, np.ndarray] = {}
        report_bytes = 0
        if self.reporter is not None and self.setting.noise_reports:
            known, noise = self.reporter.report(sent_ids, sent)
            if self.radio:
                report = NoiseReportMessage(self.drone_id, step, known, noise).encode()
                payload, report_bytes = payload + report, len(report)
                decoded = NoiseReportMessage.decode(report)
                known, noise = decoded.target_ids, decoded.noise
            reports = dict(zip(known, noise, strict=True))
        elif self.reporter is not None:  # the bias correction's residual only
            self.reporter.remember(sent_ids, sent)
        positions = np.array(positions, dtype=float)
        positions[send] = sent
        return Uplink(
            self.drone_id, step, ids, positions, send, reports, payload, prediction_bytes,
            report_bytes,
        )  # fmt: skip

    def install(self, predictor: TrajectoryPredictor) -> None:
        """Fly ``predictor`` (a round's model) from now on; with the bias correction its bias
        is re-estimated on the record (:meth:`~dronefl.tracking.reports.NoiseReporter.rebase`),
        as the old model's is not the new one's."""
        self.predictor = predictor
        if self.setting.correct_bias:
            self.reporter.rebase(
                self.record, predictor, self.past_steps, self.setting.detected_only
            )
