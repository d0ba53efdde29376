"""The YOLO detector's measured quality as typed results (SPEC §3).

:func:`~dronefl.perception.evaluation.evaluate_detector` measures a :class:`DetectorReport`
(``eval.json``); the shipped sidecar ``detector.json`` keeps each environment's
:class:`EnvironmentMetrics` (the report without the per-bin rows). Both are serialised by
:mod:`dronefl.serialize`, the Ultralytics metrics under their usual keys ``mAP50`` and
``mAP50-95``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dronefl.perception.projection import ProjectionNoise
from dronefl.serialize import json_key, load_result, omitted_when_none, save_result


@dataclass(frozen=True)
class AltitudeRow:
    """The labelled vehicles (visible fraction >= 0.5) seen from one altitude bin.

    ``altitude_m`` the bin, ``"15-25"`` (m) or ``"all"``; ``vehicles`` their count;
    ``miss_rate`` the fraction not found; ``center_rms_px`` the RMS per-axis centre error of the
    found ones (px of the 640 px frame); ``size_rms`` the RMS relative size error
    (``w_det / w_true - 1``, ``h_det / h_true - 1``). NaN where the bin holds no vehicle (or
    none was found). ``false_per_frame``: false reports per frame, on the ``"all"`` row only.
    """

    altitude_m: str
    vehicles: int
    miss_rate: float
    center_rms_px: float
    size_rms: float
    false_per_frame: float | None = omitted_when_none()


@dataclass(frozen=True)
class EnvironmentReport:
    """One environment's test frames: their count, Ultralytics' ``map50`` and ``map50_95``
    (COCO-style AP at IoU 0.5 and averaged over 0.5-0.95) and the errors ``by_altitude``
    (the bins, then ``"all"``)."""

    frames: int
    map50: float = json_key("mAP50")
    map50_95: float = json_key("mAP50-95")
    by_altitude: tuple[AltitudeRow, ...]

    @property
    def overall(self) -> AltitudeRow:
        """The ``"all"`` row of :attr:`by_altitude`."""
        return self.by_altitude[-1]

    @property
    def bins(self) -> tuple[AltitudeRow, ...]:
        """The rows of the altitude bins (all but ``"all"``)."""
        return self.by_altitude[:-1]


@dataclass(frozen=True)
class NoiseFit:
    """The projection detector's noise model ``before`` (hand-set) and ``after`` the fit."""

    before: ProjectionNoise
    after: ProjectionNoise


@dataclass(frozen=True)
class DetectorReport:
    """The evaluation of the ONNX ``weights`` on the ``dataset`` folder's held-out frames:
    one :class:`EnvironmentReport` per environment and the fitted ``projection_noise``."""

    weights: Path
    dataset: Path
    environments: dict[str, EnvironmentReport]
    projection_noise: NoiseFit

    def save(self, path: Path) -> Path:
        """Write the report to ``path`` (``eval.json``)."""
        return save_result(path, self)

    @classmethod
    def load(cls, path: Path) -> DetectorReport:
        """Read an ``eval.json``; :class:`~dronefl.serialize.ResultError` names a bad file."""
        return load_result(cls, path)


@dataclass(frozen=True)
class EnvironmentMetrics:
    """What the sidecar keeps of an :class:`EnvironmentReport`: frames, ``map50``,
    ``map50_95`` and the ``overall`` (``"all"``) row."""

    frames: int
    map50: float = json_key("mAP50")
    map50_95: float = json_key("mAP50-95")
    overall: AltitudeRow = json_key("all")

    @classmethod
    def of(cls, report: EnvironmentReport) -> EnvironmentMetrics:
        """The sidecar's summary of ``report``."""
        return cls(report.frames, report.map50, report.map50_95, report.overall)
