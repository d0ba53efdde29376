"""run_bench and the command: inputs checked before any work, bench.json and bench.md written."""

import json
from time import perf_counter

import pytest
import typer
from typer.testing import CliRunner

from dronefl.bench import run
from dronefl.bench.cloud import WARMUP_STEPS
from dronefl.bench.command import bench
from dronefl.bench.results import Benchmarks, BenchResults
from dronefl.bench.run import BenchError, run_bench
from dronefl.bench.timing import latency
from dronefl.serialize import load_result


@pytest.fixture
def stub_groups(monkeypatch):
    """Replace the benchmark groups by stubs that record that they ran."""
    ran = []

    def group(name):
        def measure(ctx):
            ran.append(name)
            return Benchmarks(**{name: latency(name, [1e-3, 2e-3, 3e-3], "ms", 1)})

        return measure

    monkeypatch.setattr(run, "GROUPS", {"cloud": group("planner"), "vision": group("detector")})
    return ran


def test_an_out_that_is_a_file_fails_before_any_benchmark(tmp_path, stub_groups):
    not_a_folder = tmp_path / "bench.txt"
    not_a_folder.write_text("x")

    with pytest.raises(BenchError, match="is a file, not a folder"):
        run_bench(not_a_folder, quick=True, progress=False)
    assert stub_groups == []


def test_the_command_reports_a_bad_out_in_one_line_with_exit_code_2(tmp_path, stub_groups):
    not_a_folder = tmp_path / "bench.txt"
    not_a_folder.write_text("x")
    app = typer.Typer()
    app.command()(bench)

    result = CliRunner().invoke(app, ["--out", str(not_a_folder), "--quick"])

    assert result.exit_code == 2
    assert result.output.strip() == f"error: --out: {not_a_folder} is a file, not a folder"
    assert stub_groups == []


def test_an_unknown_group_is_rejected(tmp_path, stub_groups):
    with pytest.raises(BenchError, match="--only: unknown gpu"):
        run_bench(tmp_path, only=("gpu",), progress=False)


def test_run_bench_writes_json_and_markdown(tmp_path, stub_groups):
    results = run_bench(tmp_path / "bench", quick=True, progress=False)

    written = json.loads((tmp_path / "bench" / "bench.json").read_text())
    assert load_result(BenchResults, tmp_path / "bench" / "bench.json") == results
    assert stub_groups == ["planner", "detector"]
    assert {"schema", "quick", "machine", "benchmarks", "energy", "goals", "sizes"} <= set(written)
    assert list(written["benchmarks"]) == ["planner", "detector"]
    assert results.machine.cores_visible >= 1 and results.machine.cpu_model
    assert results.energy.estimates["detector"].kind == "estimate"
    assert "## Table II" in (tmp_path / "bench" / "bench.md").read_text()
    assert sorted(p.name for p in (tmp_path / "bench").iterdir()) == ["bench.json", "bench.md"]


def test_quick_cloud_group_measures_fusion_and_planner(tmp_path):
    started = perf_counter()
    results = run_bench(tmp_path, quick=True, only=("cloud",), progress=False)
    elapsed = perf_counter() - started

    fusion, planner = results.benchmarks.fusion, results.benchmarks.planner
    steps = results.sizes.cloud_steps - WARMUP_STEPS  # the warm-up steps are not timed
    for figure in (fusion, planner, fusion.reference):
        assert figure.unit == "ms" and figure.threads == 1 and figure.samples == steps
        # Half the steps take the median or longer, and all of them ran within `elapsed`.
        assert 0 < steps / 2 * figure.median * 1e-3 <= elapsed
        assert figure.median <= figure.p95
    assert results.groups == ("cloud",)
    planner_goal = next(g for g in results.goals if g.goal.startswith("planner"))
    assert planner_goal.value == planner.median and planner_goal.met is not None
