"""Scenario validation: the shipped cases load; every bad file fails with its own message."""

import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dronefl.config import (
    MAX_SCENARIO_BYTES,
    ScenarioError,
    builtin_scenarios,
    load_scenario,
    scenario_path,
)

BAD = Path(__file__).parent / "data" / "bad_scenarios"
FARM = Path(__file__).parent / "data" / "scenarios" / "farm_5x8.yaml"
NOT_A_NAME = "is not a name of 1-64 ASCII letters, digits"

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
    "zero_rate": "rate_hz: Input should be greater than or equal to 1",
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
    "alias_bomb": "YAML anchors and aliases (&, *) are not allowed in a scenario (line 1)",
    "deep_nesting": "YAML nested deeper than 16 levels (line 1)",
    "name_absolute": f"name: '/tmp/evil' {NOT_A_NAME}",
    "name_dotdot": f"name: '..' {NOT_A_NAME}",
    "name_slash": f"name: 'a/b' {NOT_A_NAME}",
    "name_empty": f"name: '' {NOT_A_NAME}",
    "name_unicode_space": f"name: 'drône 1' {NOT_A_NAME}",
    "altitude_inf": "drones[0].altitude: Input should be a finite number (got inf)",
    "altitude_nan": "drones[0].altitude: Input should be a finite number (got nan)",
    "altitude_huge": "drones[0].altitude: Input should be less than or equal to 150 (got 1e+308)",
    "speed_huge": "targets[0].speed: Input should be less than or equal to 5 (got 1e+30)",
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


def test_alias_bomb_is_refused_before_it_expands():
    # Prepare: 342 bytes whose last anchor expands to 9^9 strings (> 2.9 GB as JSON).
    path = BAD / "alias_bomb.yaml"
    assert path.stat().st_size < 400
    # Execute
    start = time.perf_counter()
    with pytest.raises(ScenarioError, match=rf"^{re.escape(str(path))}: YAML anchors") as info:
        load_scenario(path)
    seconds = time.perf_counter() - start
    # Assert
    assert seconds < 1.0
    assert "\n" not in str(info.value)


def test_a_file_over_the_size_limit_is_refused_unread(tmp_path):
    # Prepare: a valid scenario padded with YAML comments to one byte over the limit.
    path = tmp_path / "huge.yaml"
    text = FARM.read_text()
    path.write_text(text + "#" * (MAX_SCENARIO_BYTES - len(text.encode())) + "\n")
    # Execute / Assert
    with pytest.raises(ScenarioError, match=rf"^{re.escape(str(path))}: larger than the"):
        load_scenario(path)


def test_a_file_at_the_size_limit_loads(tmp_path):
    # Prepare: the same padding, one byte shorter.
    path = tmp_path / "padded.yaml"
    text = FARM.read_text()
    path.write_text(text + "#" * (MAX_SCENARIO_BYTES - len(text.encode()) - 1) + "\n")
    assert path.stat().st_size == MAX_SCENARIO_BYTES
    # Execute / Assert
    assert load_scenario(path) == load_scenario(FARM)


@pytest.mark.parametrize("name", [*builtin_scenarios(), str(FARM)])
def test_every_shipped_scenario_loads(name):
    scenario = load_scenario(name)
    assert scenario.name == Path(scenario_path(name)).stem


def test_the_content_hash_of_a_valid_scenario_is_unchanged_by_validation():
    # The pretrained cache is keyed by this hash: stricter validation must not re-key it.
    assert load_scenario(FARM).content_hash == "1d066e637b7b"


@pytest.mark.parametrize("name", ["case1-altitude-29.9m", "farm_5x8", "A", "x" * 64])
def test_a_folder_safe_name_loads(tmp_path, name):
    # Prepare
    path = tmp_path / "named.yaml"
    path.write_text(FARM.read_text().replace("name: farm_5x8", f"name: {name}"))
    # Execute / Assert
    assert load_scenario(path).name == name


#: YAML for names that are no folder name: too long, hidden, a newline, a backslash, a space.
@pytest.mark.parametrize("name", ["x" * 65, ".hidden", '"a\\nb"', "'C:\\x'", "'a b'"])
def test_a_name_that_is_no_safe_folder_name_is_refused(tmp_path, name):
    # Prepare
    path = tmp_path / "named.yaml"
    path.write_text(FARM.read_text().replace("name: farm_5x8", f"name: {name}"))
    # Execute / Assert
    with pytest.raises(
        ScenarioError, match=rf"^{re.escape(str(path))}: name: .* {NOT_A_NAME}"
    ) as info:
        load_scenario(path)
    assert "\n" not in str(info.value)
