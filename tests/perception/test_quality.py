"""The detector's results keep their JSON files: eval.json round-trips, the shipped sidecar and
noise fit load and are rewritten byte for byte."""

import json
import math
from dataclasses import replace
from pathlib import Path

from dronefl.perception.projection import FITTED_NOISE_ASSET, FittedNoise, ProjectionNoise
from dronefl.perception.quality import (
    AltitudeRow,
    DetectorReport,
    EnvironmentMetrics,
    EnvironmentReport,
    NoiseFit,
)
from dronefl.perception.training import DetectorSidecar, detector_sidecar
from dronefl.perception.yolo import shipped_detector_path
from dronefl.serialize import from_json, save_result


def _report(empty_bin_miss_rate: float = 0.1) -> DetectorReport:
    rows = (
        AltitudeRow("15-25", 10, empty_bin_miss_rate, 1.25, 0.05),
        AltitudeRow("all", 10, 0.1, 1.25, 0.05, false_per_frame=0.5),
    )
    return DetectorReport(
        Path("weights/detector.onnx"),
        Path("data/set"),
        {"crop_field": EnvironmentReport(4, 0.98, 0.82, rows)},
        NoiseFit(ProjectionNoise(), ProjectionNoise(center_px=2.0)),
    )


def test_detector_report_round_trips_through_eval_json(tmp_path: Path) -> None:
    report = _report()
    path = report.save(tmp_path / "eval.json")
    assert DetectorReport.load(path) == report
    data = json.loads(path.read_text())
    assert list(data) == ["weights", "dataset", "environments", "projection_noise"]
    env = data["environments"]["crop_field"]
    assert list(env) == ["frames", "mAP50", "mAP50-95", "by_altitude"]
    assert "false_per_frame" not in env["by_altitude"][0]
    assert env["by_altitude"][1]["false_per_frame"] == 0.5
    assert list(data["projection_noise"]) == ["before", "after"]
    assert data["projection_noise"]["after"]["center_px"] == 2.0


def test_nan_of_an_empty_bin_comes_back_as_nan(tmp_path: Path) -> None:
    path = _report(empty_bin_miss_rate=float("nan")).save(tmp_path / "eval.json")
    loaded = DetectorReport.load(path)
    assert math.isnan(loaded.environments["crop_field"].bins[0].miss_rate)


def test_sidecar_metrics_are_the_all_row() -> None:
    env = _report().environments["crop_field"]
    assert EnvironmentMetrics.of(env) == EnvironmentMetrics(4, 0.98, 0.82, env.by_altitude[-1])


def test_shipped_sidecar_and_noise_fit_are_rewritten_byte_for_byte(tmp_path: Path) -> None:
    sidecar_path = shipped_detector_path().with_name("detector.json")
    sidecar = DetectorSidecar.load(sidecar_path)
    assert sidecar.training.config.imgsz == sidecar.imgsz
    assert sidecar.metrics is not None and sidecar.metrics["orchard"].overall.altitude_m == "all"
    assert sidecar.save(tmp_path / "detector.json").read_bytes() == sidecar_path.read_bytes()
    # made again from the same inputs (dataset manifest, training record, command, metrics)
    save_result(tmp_path / "dataset" / "dataset.json", sidecar.dataset)
    remade = detector_sidecar(tmp_path / "dataset", sidecar.training, sidecar.command)
    remade = replace(remade, metrics=sidecar.metrics)
    assert remade.save(tmp_path / "remade.json").read_bytes() == sidecar_path.read_bytes()
    noise_path = sidecar_path.with_name(FITTED_NOISE_ASSET)
    noise = from_json(FittedNoise, json.loads(noise_path.read_text()))
    assert noise.params == ProjectionNoise.fitted()
    rewritten = save_result(tmp_path / FITTED_NOISE_ASSET, noise)
    assert rewritten.read_bytes() == noise_path.read_bytes()
