"""Any scenario through every closed-loop experiment: a custom 5-drone, 8-target scenario in a
200 x 150 m field (mixed constant-speed and random-walk vehicles) is simulated, pretrained from
an empty cache, flown by all three methods and tabulated; Table I reuses finished episodes;
offline FL trains every drone of it."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from dronefl.cli import app
from dronefl.config import load_scenario
from dronefl.experiments.table1 import TABLE1_METHODS, episode_configs, run_table1
from dronefl.experiments.track import TrackConfig
from dronefl.results.episode import EpisodeMetrics
from dronefl.results.fl import OfflineResults
from dronefl.results.table1 import METRICS, row_name
from dronefl.settings import Setting

#: Table I's methods with the projection detector (the image baseline flies on frames only).
TRACK_METHODS = TABLE1_METHODS["projection"]
SCENARIO = Path(__file__).parents[1] / "data" / "scenarios" / "farm_5x8.yaml"
#: Short settings: 20 s of crop field and 1 FL round to pretrain, 18 s episodes with an FL
#: round every 8 s, no GIF.
QUICK = ["pretraining.rounds=1", "pretraining.seconds=20", "learning.period=8"]
SHORT = ["--duration", "18", "--no-animate", *(a for o in QUICK for a in ("--set", o))]


def _invoke(*args: str) -> str:
    result = CliRunner().invoke(app, list(args), catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return result.output


def test_simulate_records_every_drone_of_the_custom_scenario(tmp_path):
    _invoke("simulate", "--scenario", str(SCENARIO), "--duration", "10", "--out", str(tmp_path))

    summary = json.loads((tmp_path / "summary.json").read_text())
    assert sorted(p.name for p in tmp_path.glob("drone_*.npz")) == [
        f"drone_{i}.npz" for i in range(1, 6)
    ]
    assert summary["sim_seconds"] == pytest.approx(10.0)


@pytest.mark.slow
def test_offline_fl_trains_every_drone_of_the_custom_scenario(tmp_path):
    _invoke("fl-offline", "--scenario", str(SCENARIO), "--seeds", "0", "--rounds", "2",
            "--methods", "dronefl", "--duration", "30", "--stride", "5",
            "--out", str(tmp_path))  # fmt: skip

    results = OfflineResults.load(tmp_path / "results.json")
    assert results.scenario == "farm_5x8" and results.rounds == 2
    seed = results.methods["dronefl"].seed_result(0)
    assert seed is not None and len(seed.mean_test_mse) == 2
    assert sorted(seed.final_test_mse_per_drone) == [1, 2, 3, 4, 5]
    assert all(np.isfinite(v) and v > 0 for v in seed.final_test_mse_per_drone.values())
    assert all(b > 0 for b in seed.bytes_up_per_round)  # every round went over the wire


@pytest.fixture(scope="module")
def table_dir(tmp_path_factory):
    """Every method flown once (seed 0) from an empty pretrained cache, in Table I's layout."""
    root = tmp_path_factory.mktemp("any_scenario")
    pretrained = root / "pretrained"
    for method in TRACK_METHODS:
        out = root / "table" / "farm_5x8" / method / "seed0"
        _invoke("track", "--scenario", str(SCENARIO), "--method", method, *SHORT,
                "--env", "orchard", "--pretrained", str(pretrained), "--out", str(out))  # fmt: skip
    return root


@pytest.mark.parametrize("method", TRACK_METHODS)
@pytest.mark.slow
def test_every_method_flies_the_custom_scenario(table_dir, method):
    metrics = EpisodeMetrics.load(
        table_dir / "table" / "farm_5x8" / method / "seed0" / "metrics.json"
    )

    assert metrics.scenario == "farm_5x8" and metrics.method == method
    assert metrics.communication.drone_ids == (1, 2, 3, 4, 5)
    assert metrics.tracking.prediction_coverage > 0.5
    # The learners update at 8 s and 16 s; the fixed models never do.
    assert len(metrics.fl_rounds) == (0 if method == "fixed" else 2)
    if method == "dronefl":
        assert metrics.communication.kb_per_s(kind="weights") > 0
        assert all(set(r.train_loss) == {1, 2, 3, 4, 5} for r in metrics.fl_rounds)


def test_pretraining_filled_the_empty_cache_once_per_kind(table_dir):
    folder = table_dir / "pretrained" / "farm_5x8"
    kinds = sorted(p.name.split("-")[0] for p in folder.iterdir() if not p.name.startswith("data"))
    # detection_gaps = "auto": DroneFL's model at both candidates, the orchard validation flight
    # and the choice; the centralized model once, at the chosen probability.
    assert kinds == ["centralized", "dronefl", "dronefl", "gaps", "orchard"]
    assert len(list(folder.glob("data-*"))) == 1  # one recording shared by all


def test_table1_reuses_the_finished_episodes(table_dir):
    out = table_dir / "table"
    before = {p: p.stat().st_mtime_ns for p in out.rglob("metrics.json")}
    base = TrackConfig(
        scenario=load_scenario(SCENARIO), out=out, duration=18.0,
        setting=Setting.load("recommended", QUICK), pretrained=table_dir / "pretrained",
    )  # fmt: skip

    episodes = run_table1(base, (base.scenario,), TRACK_METHODS, seeds=(0,))

    assert [e.method for e in episodes] == list(TRACK_METHODS)
    assert {p: p.stat().st_mtime_ns for p in out.rglob("metrics.json")} == before
    table = (out / "table1.md").read_text()
    for method, episode in zip(TRACK_METHODS, episodes, strict=True):
        (line,) = [row for row in table.splitlines() if f"| farm_5x8 | {method} (n=1) |" in row]
        distances, tracking = episode.set_distances, episode.tracking
        sent, fused = tracking.sent_prediction_error, tracking.tracking_error
        ospa, gospa = distances.ospa, distances.gospa
        assert (
            f"| {sent:.3f} ± 0.000 | {fused:.3f} ± 0.000 | {ospa:.2f} ± 0.00 | {gospa:.2f} ± 0.00 |"
            in line
        )
    assert "farm_5x8: DroneFL vs fixed distributed: prediction error" in table
    assert "on the predictions sent), tracking distance" in table
    header, *lines = (out / "table1.csv").read_text().splitlines()
    assert header.split(",")[3:-1] == [
        *METRICS,
        "sent_prediction_error",
        "tracking_error",
        "ospa",
        "gospa",
    ]
    assert [float(v) for v in lines[0].split(",")[-3:-1]] == [
        episodes[0].set_distances.ospa,
        episodes[0].set_distances.gospa,
    ]
    assert (out / "table1.png").stat().st_size > 10_000


@pytest.mark.slow
def test_table1_adds_dronefl_s_label_ablation_rows(table_dir, tmp_path):
    # Issue #14's label-ablation rows: DroneFL again with filtered and ground-truth labels,
    # beside the finished episodes (reused), as rows of their own in every output.
    out = tmp_path / "table"
    shutil.copytree(table_dir / "table", out)
    base = TrackConfig(
        scenario=load_scenario(SCENARIO), out=out, duration=18.0,
        setting=Setting.load("recommended", QUICK), pretrained=table_dir / "pretrained",
    )  # fmt: skip
    with pytest.raises(ValueError, match="--label-ablation"):
        episode_configs(base, (base.scenario,), ("fixed",), (0,), label_ablation=True)

    episodes = run_table1(base, (base.scenario,), ("fixed", "dronefl"), (0,), label_ablation=True)

    assert [(e.method, e.labels) for e in episodes] == [
        ("fixed", "smoothed"), ("dronefl", "smoothed"),
        ("dronefl", "filtered"), ("dronefl", "ground_truth"),
    ]  # fmt: skip
    assert [row_name(e, "smoothed") for e in episodes] == [
        "fixed", "dronefl", "dronefl[labels=filtered]", "dronefl[labels=ground_truth]",
    ]  # fmt: skip
    for labels in ("filtered", "ground_truth"):
        assert (out / "farm_5x8" / f"dronefl-labels-{labels}" / "seed0" / "metrics.json").is_file()
    errors = [e.tracking.prediction_error for e in episodes[1:]]
    assert len(set(errors)) == 3  # three label sources, three models
    table = (out / "table1.md").read_text()
    for name, episode in zip(("dronefl[labels=filtered]", "dronefl[labels=ground_truth]"),
                             episodes[2:], strict=True):  # fmt: skip
        (line,) = [row for row in table.splitlines() if f"| farm_5x8 | {name} (n=1) |" in row]
        assert f"| {episode.tracking.prediction_error:.2f} ± 0.00 |" in line
    names = [line.split(",")[1] for line in (out / "table1.csv").read_text().splitlines()[1:]]
    assert names == [row_name(e, "smoothed") for e in episodes]
