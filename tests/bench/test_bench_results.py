"""bench.json: a hand-made BenchResults saved and loaded back, with the keys of its figures."""

import json
import math
from dataclasses import replace

import pytest

from dronefl.bench.energy import RPI5_INFERENCE, EnergyReading, RaplStatus, estimate
from dronefl.bench.machine import LoadAverage, MachineInfo
from dronefl.bench.results import (
    BenchEnergy,
    Benchmarks,
    BenchResults,
    BenchSizes,
    ClosedLoopFigure,
    CommFigure,
    EnvironmentUplink,
    EpisodeSpeed,
    GoalResult,
    SimulatorFigure,
    UplinkFigure,
)
from dronefl.bench.timing import latency, with_reference
from dronefl.serialize import load_result, save_result


def _benchmarks() -> Benchmarks:
    # Fusion: ours 2 ms per step, filterpy 5 ms, both on every one of 3 steps.
    fusion = with_reference(
        replace(latency("ours", [2e-3] * 3, "ms", 1), measurements_per_step=19.5),
        latency("filterpy", [5e-3] * 3, "ms", 1),
    )
    detector = replace(
        latency("yolo", [8e-3, 9e-3], "ms", 1),
        per_environment={"orchard": latency("yolo, orchard", [8e-3, 9e-3], "ms", 1)},
        paper_ms=130.0,
        energy_reading=EnergyReading("reading", 0.05, 2, 6.0, "a fake meter"),
    )
    fixed = EpisodeSpeed("fixed models", 50.0, 50.0, 12.0, 0.0, 0, 1.5, 14.0)
    return Benchmarks(
        fusion=fusion,
        planner=latency("plan", [1e-3, 2e-3, 3e-3], "ms", 1),
        simulator=SimulatorFigure(
            "sim", "x real time", {"crop_field": 400.0, "orchard": 250.0}, 250.0, 10.0, 1
        ),
        detector=detector,
        centralized_uplink=UplinkFigure(
            "jpeg",
            "KB/s",
            495.0,
            "orchard",
            {"orchard": EnvironmentUplink(495.0, {1: 490.0, 2: 500.0}, 8, 99.0)},
            2460.0,
        ),
        closed_loop=ClosedLoopFigure(
            "dronefl", "x real time", 20.0, 45.0, 30.0, 16.0, 5, 1.5, 33.0, "1", fixed, 0.4
        ),
        # No FL round ran: NaN per round and at one round per period (null in the JSON).
        dronefl_comm=CommFigure(
            what="comm",
            unit="KB/s",
            kb_per_s=0.27,
            at_fl_period=math.nan,
            fl_period_s=100.0,
            fl_rounds=0,
            weights_kb_per_round=math.nan,
            by_type={"up:predictions": 0.2},
            drones={1: 0.27, 2: 0.27},
            paper_kb_per_s=1.56,
            weights_dtype="float32",
        ),
    )


def _results() -> BenchResults:
    benchmarks = _benchmarks()
    return BenchResults(
        schema=1,
        quick=True,
        scenario="case3",
        started="2026-01-01 00:00:00 UTC",
        wall_seconds=12.5,
        groups=("cloud", "simulator", "vision", "closed_loop"),
        sizes=BenchSizes(),
        machine=MachineInfo(
            cpu_model="AMD EPYC",
            cores_visible=2,
            platform="Linux",
            python="3.11.7",
            versions={"numpy": "2.4", "filterpy": None},
            load_average=LoadAverage(start=(1.41, 1.0, 0.8), end=None),
        ),
        benchmarks=benchmarks,
        energy=BenchEnergy(
            RaplStatus(True, zones=("/sys/class/powercap/intel-rapl:0",)),
            {"detector": estimate(8.5e-3, RPI5_INFERENCE)},
        ),
        goals=(
            GoalResult("planner", "<= 5 ms", 2.0, "ms", True),
            GoalResult("closed loop", ">= 20 x real time", math.nan, "x real time", None),
        ),
    )


def test_bench_results_round_trip_through_bench_json_with_the_reference_ratio(tmp_path):
    results = _results()

    path = save_result(tmp_path / "bench.json", results)
    loaded = load_result(BenchResults, path)

    assert loaded == results
    fusion = loaded.benchmarks.fusion
    assert (fusion.median, fusion.reference.median) == pytest.approx((2.0, 5.0))
    assert fusion.ratio == pytest.approx(2.5)  # 5 ms / 2 ms: ours is 2.5 times faster
    written = json.loads(path.read_text())
    figures = written["benchmarks"]
    assert list(figures) == [
        "fusion", "planner", "simulator", "detector", "centralized_uplink", "closed_loop",
        "dronefl_comm",
    ]  # fmt: skip
    # A figure's JSON holds only the keys it carries: a plain latency has no reference or ratio.
    assert list(figures["planner"]) == ["what", "unit", "median", "p95", "samples", "threads"]
    assert list(figures["fusion"])[6:] == ["measurements_per_step", "reference", "ratio"]
    assert figures["dronefl_comm"]["at_fl_period"] is None
    assert figures["centralized_uplink"]["per_environment"]["orchard"]["drones"] == {
        "1": 490.0,
        "2": 500.0,
    }
    assert written["energy"]["rapl"] == {
        "available": True,
        "zones": ["/sys/class/powercap/intel-rapl:0"],
    }
    assert written["goals"][1]["value"] is None and written["goals"][1]["met"] is None
