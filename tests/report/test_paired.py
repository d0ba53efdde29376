"""The paired comparison of two methods over seeds (``dronefl fl-compare``), checked by hand."""

import math

import pytest
from typer.testing import CliRunner

from dronefl.cli import app
from dronefl.experiments.fl_offline import comparison_table
from dronefl.report.paired import paired_comparison, table1_comparison
from dronefl.results.fl import MethodResult, OfflineResults, SeedResult


def _method(name: str, per_seed: dict[int, dict[int, float]]) -> MethodResult:
    seeds = tuple(
        SeedResult(seed, (sum(mse.values()) / len(mse),), mse, (0,), (0,), {}, 1.0)
        for seed, mse in per_seed.items()
    )
    return MethodResult(name, "model", 1, "training", seeds)


A = _method("a", {0: {1: 1.0, 2: 0.5}, 1: {1: 2.0, 2: 0.5}, 2: {1: 3.0, 2: 0.5}, 7: {1: 9, 2: 9}})
B = _method("b", {0: {1: 2.0, 2: 0.5}, 1: {1: 2.0, 2: 0.5}, 2: {1: 5.0, 2: 0.5}})


def test_differences_standard_error_wins_and_p_by_hand():
    one, two = paired_comparison(A, B)

    # Drone 1: d = (-1, 0, -2) over the shared seeds 0-2 (A's seed 7 has no partner).
    assert one.seeds == (0, 1, 2)
    assert (one.mean_a, one.mean_b) == (2.0, 3.0) and one.ratio == pytest.approx(2 / 3)
    assert one.mean_difference == pytest.approx(-1.0)
    assert one.standard_error == pytest.approx(1 / math.sqrt(3))  # std(d, ddof=1) = 1
    assert one.wins == 2  # seed 1 is a tie, not a win
    # t = -1 / (1 / sqrt 3) = -sqrt 3 with 2 dof, whose two-sided p has a closed form:
    # p = 1 - |t| / sqrt(t^2 + 2) = 1 - sqrt(3 / 5).
    assert one.p_value == pytest.approx(1 - math.sqrt(3 / 5))
    # Drone 2: identical errors, no difference to test.
    assert two.mean_difference == 0.0 and two.wins == 0 and math.isnan(two.p_value)


def test_fewer_than_two_shared_seeds_or_other_drones_are_refused():
    lone = _method("c", {7: {1: 1.0, 2: 1.0}, 8: {1: 1.0, 2: 1.0}})
    with pytest.raises(ValueError, match="share 0 seed"):
        paired_comparison(B, lone)
    other = _method("d", {0: {1: 1.0}, 1: {1: 1.0}})
    with pytest.raises(ValueError, match=r"drones \(1, 2\).*\(1,\)"):
        paired_comparison(A, other)


def test_the_command_prints_the_table_and_names_a_missing_method(tmp_path):
    results = tmp_path / "results.json"
    OfflineResults("case9", "recommended", "0123456789ab", 1, 60.0, 5, {"a": A, "b": B}).save(
        results
    )
    runner = CliRunner()

    shown = runner.invoke(app, ["fl-compare", str(results), "a", "b"])
    assert shown.exit_code == 0, shown.output
    assert "case9, final test MSE per drone, seeds 0 1 2" in shown.output
    assert "| 1 | 2.000 | 3.000 | 0.67 | -1.000 ± 0.577 | 2 of 3 seeds | 0.23 |" in shown.output

    missing = runner.invoke(app, ["fl-compare", str(results), "a", "local"])
    assert missing.exit_code == 2
    assert f"{results}: no method 'local'" in missing.output


TABLE1 = """scenario,method,seed,prediction_error,tracking_distance
case2,fixed,0,1.5,20.0
case2,fixed,1,1.0,21.0
case2,dronefl,0,1.0,20.5
case2,dronefl,1,0.8,21.0
case2,dronefl,2,0.1,1.0
case9,dronefl,0,1.0,1.0
"""


def test_table1_rows_pair_each_scenario_s_seeds(tmp_path):
    path = tmp_path / "table1.csv"
    path.write_text(TABLE1)

    (case2,) = table1_comparison(path, "dronefl", "fixed", "prediction_error")

    # Seeds 0 and 1 only (fixed has no seed 2; case9 has no fixed): d = (-0.5, -0.2).
    assert case2.name == "case2" and case2.seeds == (0, 1)
    assert case2.mean_difference == pytest.approx(-0.35)
    assert case2.standard_error == pytest.approx(0.15)  # std(d, ddof=1) / sqrt 2 = 0.212 / 1.414
    assert case2.wins == 2
    # t = -0.35 / 0.15 with 1 dof (a Cauchy distribution): p = 1 - (2 / pi) atan(|t|).
    assert case2.p_value == pytest.approx(1 - 2 / math.pi * math.atan(0.35 / 0.15))
    (distance,) = table1_comparison(path, "dronefl", "fixed", "tracking_distance")
    assert distance.mean_difference == pytest.approx(0.25) and distance.wins == 0
    with pytest.raises(ValueError, match=r"table1.csv: no column 'ospa' \(it has prediction_error"):
        table1_comparison(path, "dronefl", "fixed", "ospa")
    with pytest.raises(ValueError, match=r"no method 'local' \(it has \['dronefl', 'fixed'\]\)"):
        table1_comparison(path, "local", "fixed", "prediction_error")

    shown = CliRunner().invoke(app, ["table1-compare", str(path), "dronefl", "fixed"])
    assert shown.exit_code == 0, shown.output
    assert "prediction_error, seeds 0 1:" in shown.output
    assert "| case2 | 0.900 | 1.250 | 0.72 | -0.350 ± 0.150 | 2 of 2 seeds | 0.26 |" in shown.output


def test_fig5_s_table_pairs_dronefl_with_local_when_both_ran():
    results = OfflineResults(
        "case9", "recommended", "0123456789ab", 1, 60.0, 5, {"dronefl": A, "local": B}
    )
    table = comparison_table([results], ("dronefl", "local"))

    assert "case9: DroneFL against `local` per drone, paired over the seeds" in table
    assert "| 1 | 2.000 | 3.000 | 0.67 | -1.000 ± 0.577 | 2 of 3 seeds | 0.23 |" in table
    alone = OfflineResults("case9", "recommended", "0123456789ab", 1, 60.0, 5, {"dronefl": A})
    assert "paired" not in comparison_table([alone], ("dronefl",))
