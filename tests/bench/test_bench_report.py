"""Goals, energy estimates, Table II and bench.md from hand-made results."""

import math

import pytest

from dronefl.bench.energy import RPI5_INFERENCE, RPI5_TRAINING, RaplStatus
from dronefl.bench.machine import LoadAverage, MachineInfo
from dronefl.bench.report import (
    GOALS,
    energy_estimates,
    evaluate_goals,
    fmt,
    markdown,
    summary_line,
    table2,
)
from dronefl.bench.results import BenchEnergy, Benchmarks, BenchResults, BenchSizes, CommFigure
from dronefl.bench.timing import latency, with_reference


def _figures() -> Benchmarks:
    predictor = with_reference(
        latency("ours", [0.2e-3] * 3, "ms", 1), latency("stock", [0.6e-3] * 3, "ms", 1)
    )
    return Benchmarks(
        predictor_inference=predictor,
        centralized_inference=latency("large", [0.4e-3] * 3, "ms", 1),
        training_epoch=latency("epoch", [0.25] * 3, "s", 1),
        centralized_training_epoch=latency("large epoch", [1.0] * 3, "s", 1),
        image_inference=latency("image", [2e-3] * 3, "ms", 1),
        image_training_epoch=latency("image epoch", [9.0] * 3, "s", 1),
        detector=latency("yolo", [60e-3] * 3, "ms", 1),
        planner=latency("plan", [2e-3] * 3, "ms", 1),
    )


def _results(figures: Benchmarks) -> BenchResults:
    versions = {"torch": "t", "onnxruntime": "o", "flwr": "f", "numpy": "n"}
    return BenchResults(
        schema=1,
        quick=False,
        scenario="case3",
        started="today",
        wall_seconds=1.0,
        groups=("cloud", "predictor", "vision"),
        sizes=BenchSizes(),
        machine=MachineInfo("AMD EPYC", 2, "Linux", "3.11", versions, LoadAverage(None, None)),
        benchmarks=figures,
        energy=BenchEnergy(
            RaplStatus(False, reason="not available: none"), energy_estimates(figures)
        ),
        goals=evaluate_goals(figures),
    )


def _comm(kb_per_s: float, at_fl_period: float) -> CommFigure:
    return CommFigure("comm", "KB/s", kb_per_s, at_fl_period, 100.0, 5, 60.0, {}, {}, 1.56, "")


def test_goals_are_judged_against_their_limits():
    goals = {g.goal: g for g in evaluate_goals(_figures())}

    assert len(goals) == len(GOALS)
    assert goals["predictor, one drone step (6 targets)"].met is True  # 0.2 <= 0.3 ms
    assert goals["detector, one 640x640 frame"].met is False  # 60 > 50 ms
    assert goals["Case 3 closed loop with DroneFL"].met is None  # not measured
    assert math.isnan(goals["Case 3 closed loop with DroneFL"].value)
    assert goals["Case 3 closed loop with DroneFL"].target == ">= 20 x real time"


def test_energy_estimates_use_the_median_latency_in_seconds():
    estimates = energy_estimates(_figures())

    assert estimates["detector"].joules == pytest.approx(60e-3 * RPI5_INFERENCE.watts)
    assert estimates["predictor"].joules == pytest.approx(0.2e-3 * RPI5_INFERENCE.watts)
    assert estimates["training_epoch"].joules == pytest.approx(0.25 * RPI5_TRAINING.watts)
    assert {e.kind for e in estimates.values()} == {"estimate"}


def test_table2_puts_ours_beside_the_papers_numbers():
    rows = {row[0]: row for row in table2(_results(_figures()))}

    latency_row = rows["Infer. latency per sample (s)"]
    assert latency_row[1:3] == ("0.63", "0.13 (Y.) + 0.01 (T.)")
    assert latency_row[4] == "0.0602 = 0.06 (Y.) + 0.0002 (T.)"
    assert latency_row[5] == "0.002"  # the image model: no detector
    assert rows["Train. latency per epoch (s)"][3:] == ("1", "0.25", "9")
    assert "Infer. energy per sample (J, estimate)" in rows
    assert rows["Communication cost (KB/s per drone)"][3:] == ("—", "—", "—")  # not measured


def test_table2_gives_dronefl_comm_at_one_round_per_period_or_says_there_was_none():
    # fp32: 1.15 KB/s at one round per 100 s, 0.994 over the episode; fp16: no round ran.
    figures = Benchmarks(dronefl_comm=_comm(0.994, 1.15), dronefl_comm_fp16=_comm(0.5, math.nan))

    rows = {row[0]: row for row in table2(_results(figures))}

    assert rows["Communication cost (KB/s per drone)"][4] == (
        "1.15 fp32 (episode: 0.994) / 0.5 fp16 (no FL round)"
    )


def test_markdown_labels_energy_as_an_estimate_and_lists_every_figure():
    text = markdown(_results(_figures()))

    assert "AMD EPYC, 2 cores visible" in text
    assert "energy estimate (J)" in text and "not measurements" in text
    assert "## Table II" in text
    assert text.count("\n| ") >= len(_figures().items()) + len(GOALS) + 5


def test_summary_line_names_threads_reference_and_ratio():
    line = summary_line("predictor_inference", _figures().predictor_inference)
    assert line == "predictor_inference: 0.2 ms (p95 0.2) [threads: 1]; stock: 0.6 ms (ratio 3x)"


@pytest.mark.parametrize(
    ("value", "text"), [(None, "—"), (0.000123456, "0.000123"), (2460.0, "2,460"), (48.2, "48.2")]
)
def test_fmt(value, text):
    assert fmt(value) == text
