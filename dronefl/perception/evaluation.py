"""Measured quality of the YOLO detector, and the projection noise model fitted to it (SPEC §3).

On the held-out test frames of each environment (``test_crop_field``, ``test_orchard``):

* **mAP50, mAP50-95**: Ultralytics' detection validator run on the exported ONNX network
  (COCO-style 101-point AP, all boxes with confidence >= 0.001, its own NMS);
* **the shipped detector path** (:class:`~dronefl.perception.yolo.YoloDetector`: one box per
  target, confidence >= its threshold) against every vehicle in the frame: a vehicle counts as
  *found* when its target id is reported with IoU >= 0.5 against its projected box. From that,
  per altitude bin: miss rate of the labelled vehicles (visible fraction >= 0.5), centre error
  (px of the 640 px frame), relative size error, and false reports per frame.

The :class:`~dronefl.perception.projection.ProjectionNoise` fit:

* ``center_px``: RMS per-axis centre error of the found vehicles, px;
* ``size_frac``: RMS of ``w_det / w_true - 1`` and ``h_det / h_true - 1`` of the found vehicles;
* ``min_visible``: the visible-fraction threshold that best predicts found / not found over all
  vehicles with any part in view;
* ``miss_base``, ``miss_per_m``, ``miss_range0``: maximum likelihood of the Bernoulli model
  ``P(miss) = miss_base + miss_per_m * max(0, r - miss_range0)`` over the labelled vehicles
  (visible fraction >= 0.5), ``r`` the slant range camera -> vehicle centre, m. Partly hidden
  vehicles are left out: their misses come from occlusion, which ``min_visible`` models (the
  detector finds ~40 % of vehicles 20-30 % visible and ~80 % of those 30-50 % visible, so the
  threshold trades the two), and would otherwise be charged to range.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, replace
from importlib import resources
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.optimize import minimize

from dronefl.config import VehicleSpec, load_scenario
from dronefl.perception.dataset import DATASET_ENVIRONMENTS, LabelledScene, read_scenes
from dronefl.perception.projection import (
    FITTED_NOISE_ASSET,
    FittedNoise,
    ProjectionNoise,
    visible_boxes,
)
from dronefl.perception.quality import (
    AltitudeRow,
    DetectorReport,
    EnvironmentMetrics,
    EnvironmentReport,
    NoiseFit,
)
from dronefl.perception.training import DETECTOR_SIDECAR
from dronefl.perception.yolo import YoloDetector
from dronefl.serialize import save_result
from dronefl.sim.camera import PinholeCamera
from dronefl.sim.environment import FarmEnvironment

#: Altitude bin edges of the error tables, m.
ALTITUDE_BINS = (15.0, 25.0, 35.0, 45.0, 55.0, 70.0)
#: IoU at which a reported box counts as finding its vehicle.
MATCH_IOU = 0.5


@dataclass(frozen=True)
class VehicleOutcome:
    """One vehicle in one test frame: its ``altitude`` and slant ``range`` (m), ``visible``
    fraction, whether it is labelled, found, and the box errors when found (px, fraction)."""

    environment: str
    altitude: float
    range: float
    visible: float
    labelled: bool
    found: bool
    center_error_px: tuple[float, float] | None
    size_error: tuple[float, float] | None


def iou_xywh(a: np.ndarray, b: np.ndarray) -> float:
    """IoU of two ``(cx, cy, w, h)`` boxes (any common unit)."""
    a_lo, a_hi = a[:2] - a[2:] / 2, a[:2] + a[2:] / 2
    b_lo, b_hi = b[:2] - b[2:] / 2, b[:2] + b[2:] / 2
    inter = np.prod(np.clip(np.minimum(a_hi, b_hi) - np.maximum(a_lo, b_lo), 0, None))
    union = np.prod(a[2:]) + np.prod(b[2:]) - inter
    return float(inter / union) if union > 0 else 0.0


def score_frames(
    detector: YoloDetector, dataset: Path, environment: str
) -> tuple[list[VehicleOutcome], int, int]:
    """Run the detector on one environment's test frames; returns every vehicle's outcome, the
    number of false reports (ids not in view or boxes that match nothing) and of frames."""
    scenario = load_scenario(
        json.loads((dataset / "dataset.json").read_text())["config"]["scenario"]
    )
    camera = PinholeCamera.from_spec(scenario.camera)
    env = FarmEnvironment(environment, scenario.field)
    side = camera.detector_px
    outcomes: list[VehicleOutcome] = []
    false_reports = 0
    rows = read_scenes(dataset / "scenes" / f"test_{environment}.jsonl")
    for image_name, scene in rows:
        image = np.asarray(Image.open(dataset / "images" / f"test_{environment}" / image_name))
        detections = {d.target_id: np.array(d.box) for d in detector.detect_image(image)}
        truth = _all_vehicles(camera, scenario.vehicle, env, scene)
        labelled = set(scene.target_ids.tolist())
        matched: set[int] = set()
        for target_id, (box, visible, slant) in truth.items():
            det = detections.get(target_id)
            found = det is not None and visible > 0 and iou_xywh(det, box) >= MATCH_IOU
            if found:
                matched.add(target_id)
            outcomes.append(
                VehicleOutcome(
                    environment, float(scene.camera_position[2]), slant, visible,
                    target_id in labelled, found,
                    tuple((det[:2] - box[:2]) * side) if found else None,
                    tuple(det[2:] / box[2:] - 1.0) if found else None,
                )
            )  # fmt: skip
        false_reports += len(set(detections) - matched)
    return outcomes, false_reports, len(rows)


def _all_vehicles(
    camera: PinholeCamera, vehicle: VehicleSpec, env: FarmEnvironment, scene: LabelledScene
) -> dict[int, tuple[np.ndarray, float, float]]:
    """Projected box ``(4,)``, visible fraction and slant range (m) of every vehicle placed in
    the scene (labelled or not)."""
    if not scene.targets:
        return {}
    positions = np.array([t.position for t in scene.targets])
    headings = np.array([t.heading for t in scene.targets])
    boxes, visible = visible_boxes(
        camera, vehicle, env, scene.camera_position, 0.0, positions, headings
    )
    centres = np.concatenate([positions, np.full((len(positions), 1), vehicle.height / 2)], 1)
    slant = np.linalg.norm(centres - scene.camera_position, axis=1)
    return {
        t.target_id: (boxes[k], float(visible[k]), float(slant[k]))
        for k, t in enumerate(scene.targets)
    }


def altitude_table(
    outcomes: list[VehicleOutcome], false_reports: int, frames: int
) -> tuple[AltitudeRow, ...]:
    """Per altitude bin (and ``all``): labelled vehicles, miss rate, centre error RMS (px),
    size error RMS; ``false_per_frame`` is given for ``all`` only."""
    rows = []
    edges = ALTITUDE_BINS
    bins = [(f"{lo:.0f}-{hi:.0f}", lo, hi) for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
    for name, lo, hi in [*bins, ("all", edges[0], edges[-1])]:
        sel = [o for o in outcomes if o.labelled and lo <= o.altitude < hi + (name == "all")]
        found = [o for o in sel if o.found]
        rows.append(AltitudeRow(
            altitude_m=name,
            vehicles=len(sel),
            miss_rate=1 - len(found) / len(sel) if sel else float("nan"),
            center_rms_px=_rms([c for o in found for c in o.center_error_px]),
            size_rms=_rms([s for o in found for s in o.size_error]),
        ))  # fmt: skip
    rows[-1] = replace(rows[-1], false_per_frame=false_reports / max(frames, 1))
    return tuple(rows)


def _rms(values: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if values else float("nan")


def fit_projection_noise(outcomes: list[VehicleOutcome]) -> ProjectionNoise:
    """Fit :class:`ProjectionNoise` to measured outcomes (rules in the module doc)."""
    found = [o for o in outcomes if o.found]
    if not found:
        raise ValueError("the detector found no vehicle: nothing to fit the noise model to")
    center_px = _rms([c for o in found for c in o.center_error_px])
    size_frac = _rms([s for o in found for s in o.size_error])
    seen = [o for o in outcomes if o.visible > 0]
    visible = np.array([o.visible for o in seen])
    hit = np.array([o.found for o in seen])
    grid = np.round(np.arange(0.05, 0.96, 0.05), 2)
    accuracy = [np.mean((visible >= m) == hit) for m in grid]
    min_visible = float(grid[int(np.argmax(accuracy))])
    labelled = [o for o in outcomes if o.labelled]
    slant = np.array([o.range for o in labelled])
    missed = ~np.array([o.found for o in labelled])
    miss_base, miss_per_m, miss_range0 = _fit_miss(slant, missed)
    return ProjectionNoise(center_px, size_frac, miss_base, miss_per_m, miss_range0, min_visible)


def _fit_miss(slant: np.ndarray, missed: np.ndarray) -> tuple[float, float, float]:
    """Maximum-likelihood ``(miss_base, miss_per_m, miss_range0)`` of the hinge miss model."""

    def nll(theta: np.ndarray) -> float:
        base, per_m, r0 = theta
        p = np.clip(base + per_m * np.maximum(0.0, slant - r0), 1e-6, 1 - 1e-6)
        return float(-np.sum(np.where(missed, np.log(p), np.log1p(-p))))

    rate = float(np.clip(missed.mean(), 1e-4, 0.5))
    best = None
    for r0 in (15.0, 30.0, 45.0, 60.0):  # the hinge makes the likelihood multi-modal in r0
        res = minimize(nll, np.array([rate, 1e-3, r0]), method="L-BFGS-B",
                       bounds=[(0.0, 0.9), (0.0, 0.05), (0.0, 100.0)])  # fmt: skip
        if best is None or res.fun < best.fun:
            best = res
    return tuple(float(v) for v in best.x)


def ultralytics_map(weights: Path, dataset: Path, environment: str, imgsz: int,
                    run_dir: Path) -> tuple[float, float]:  # fmt: skip
    """``(mAP50, mAP50-95)`` from Ultralytics' validator on one environment's test split."""
    from dronefl.perception.training import prepare_ultralytics

    prepare_ultralytics(run_dir)
    from ultralytics import YOLO

    metrics = YOLO(str(weights), task="detect").val(
        data=str((dataset / f"data_{environment}.yaml").resolve()), split="test", imgsz=imgsz,
        batch=1, device="cpu", plots=False, project=str(run_dir.resolve()),
        name=f"val_{environment}", exist_ok=True, verbose=False,
    )  # fmt: skip
    return float(metrics.box.map50), float(metrics.box.map)


def evaluate_detector(
    weights: Path, dataset: Path, run_dir: Path, threads: int = 1
) -> DetectorReport:
    """Everything in the module doc, for both environments; written to ``run_dir/eval.json``."""
    if not (dataset / "dataset.json").is_file():
        raise FileNotFoundError(f"no dataset at {dataset}: run `dronefl detector dataset`")
    detector = YoloDetector(weights, threads=threads)
    environments: dict[str, EnvironmentReport] = {}
    all_outcomes: list[VehicleOutcome] = []
    for env in DATASET_ENVIRONMENTS:
        outcomes, false_reports, frames = score_frames(detector, dataset, env)
        all_outcomes += outcomes
        map50, map50_95 = ultralytics_map(weights, dataset, env, detector.imgsz, run_dir)
        table = altitude_table(outcomes, false_reports, frames)
        environments[env] = EnvironmentReport(frames, map50, map50_95, table)
    fitted = fit_projection_noise(all_outcomes)
    report = DetectorReport(weights, dataset, environments, NoiseFit(ProjectionNoise(), fitted))
    report.save(run_dir / "eval.json")
    return report


def ship_evaluation(report: DetectorReport, update_sidecar: bool) -> list[Path]:
    """Write the fitted noise to ``dronefl/assets/projection_noise.json`` (the projection
    detector's default) and, if ``update_sidecar``, the metrics into ``detector.json``."""
    assets = Path(str(resources.files("dronefl") / "assets"))
    noise = report.projection_noise
    record = FittedNoise(
        params=noise.after,
        before=noise.before,
        source="dronefl detector evaluate: YOLO detector on the held-out rendered frames",
        weights=report.weights.name,
    )
    written = [save_result(assets / FITTED_NOISE_ASSET, record)]
    if update_sidecar:
        metrics = {env: EnvironmentMetrics.of(r) for env, r in report.environments.items()}
        sidecar = replace(YoloDetector.sidecar(), metrics=metrics)
        written.append(sidecar.save(assets / DETECTOR_SIDECAR))
    return written


def format_report(report: DetectorReport) -> str:
    """Markdown tables: mAP per environment, errors by altitude, noise before/after."""
    lines = ["| environment | frames | mAP50 | mAP50-95 | miss rate | centre RMS px | "
             "size RMS | false / frame |", "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for env, r in report.environments.items():
        a = r.overall
        lines.append(
            f"| {env} | {r.frames} | {r.map50:.3f} | {r.map50_95:.3f} | "
            f"{a.miss_rate:.3f} | {a.center_rms_px:.2f} | {a.size_rms:.3f} | "
            f"{a.false_per_frame:.3f} |"
        )
    lines += ["", "| environment | altitude m | vehicles | miss rate | centre RMS px | size RMS |",
              "|---|---|---|---|---|---|"]  # fmt: skip
    for env, r in report.environments.items():
        for a in r.bins:
            lines.append(
                f"| {env} | {a.altitude_m} | {a.vehicles} | {a.miss_rate:.3f} | "
                f"{a.center_rms_px:.2f} | {a.size_rms:.3f} |"
            )
    before, after = asdict(report.projection_noise.before), asdict(report.projection_noise.after)
    lines += ["", "| ProjectionNoise | before (hand-set) | after (fitted) |", "|---|---|---|"]
    lines += [f"| {k} | {before[k]:.4g} | {after[k]:.4g} |" for k in before]
    return "\n".join(lines)
