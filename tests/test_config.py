"""Scenario validation: the shipped cases load; every bad file fails with its own message."""

import subprocess
import sys
from pathlib import Path

import pytest

from dronefl.config import ScenarioError, builtin_scenarios, load_scenario

BAD = Path(__file__).parent / "data" / "bad_scenarios"

#: file -> a fragment of the one-line message it must produce (field path first).
EXPECTED = {
    "unknown_key": "colour: unknown key",
    "unknown_nested_key": "drones[0].max_sped: unknown key",
    "wrong_type": "drones[0].altitude: Input should be a valid number",
    "number_as_string": "rate_hz: Input should be a valid number",
    "duplicate_altitude": "drones[1].altitude: 30.0 m is also drone 1's altitude",
    "missing_target": "drones[0].targets: target 7 is not in targets",
    "unwatched_target": "targets[1]: target 2 is watched by no drone",
    "negative_speed": "targets[0].speed: Input should be greater than 0",
    "zero_rate": "rate_hz: Input should be greater than 0",
    "nonpositive_field": "field.width: Input should be greater than 0",
    "duplicate_target_id": "targets[1].id: duplicate id 1",
    "unknown_motion": "targets[0].motion: Input should be 'constant_speed' or 'random_walk'",
    "lane_outside": "targets[0].lane: lane 40 is outside the field (it has 24 lanes)",
    "wrong_order": "drones[1].altitude: drones must be listed highest first",
    "missing_drones": "drones: Field required",
    "invalid_yaml": "not valid YAML (line",
    "not_a_mapping": "a scenario must be a mapping",
    "field_beyond_wire": "field.width: 400.0 m is beyond the 327.67 m that a prediction message",
    "id_beyond_byte": "targets[1].id: 300 does not fit the one-byte id",
    "footprint_too_small": "drones[0].targets: its targets start spread over 104.0 x 104.0 m",
}


def test_corpus_is_complete():
    assert {p.stem for p in BAD.glob("*.yaml")} == set(EXPECTED)


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_bad_scenario_message(name):
    path = BAD / f"{name}.yaml"
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ")
    assert EXPECTED[name] in message
    assert "\n" not in message


def test_cli_reports_bad_scenario_in_one_line_with_exit_code_2(tmp_path):
    path = BAD / "duplicate_altitude.yaml"
    out = tmp_path / "run"
    result = subprocess.run(
        [
            sys.executable,
            "-c",
            "from dronefl.cli import main; main()",
            "simulate",
            "--scenario",
            str(path),
            "--duration",
            "1",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "drones[1].altitude" in lines[0] and str(path) in lines[0]
    assert "Traceback" not in result.stderr
    assert not out.exists(), "no work may start before validation"


@pytest.mark.parametrize("name", ["case1", "case2", "case3"])
def test_builtin_cases_match_the_paper(name):
    assignments = {
        "case1": [(1,), (2,)],
        "case2": [(1, 2, 3), (1, 2), (2, 3)],
        "case3": [(1, 2, 3, 4, 5, 6), (1, 2), (3, 4), (5, 6)],
    }
    motion = {"case1": "constant_speed", "case2": "random_walk", "case3": "constant_speed"}
    scenario = load_scenario(name)
    assert name in builtin_scenarios()
    assert [d.targets for d in scenario.drones] == assignments[name]
    assert {t.motion for t in scenario.targets} == {motion[name]}
    assert {t.speed for t in scenario.targets} == {0.5}
    assert (scenario.field.width, scenario.field.height) == (160.0, 120.0)
    altitudes = [d.altitude for d in scenario.drones]
    assert altitudes == sorted(altitudes, reverse=True) and len(set(altitudes)) == len(altitudes)
    assert scenario.dt == pytest.approx(0.2)


def test_unknown_scenario_name_lists_builtins():
    with pytest.raises(ScenarioError, match="built-in scenarios: case1, case2, case3"):
        load_scenario("case9")
