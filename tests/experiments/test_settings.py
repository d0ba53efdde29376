"""Named closed-loop settings (``--setting``): what each sets, that options given beside it win,
and that ``track``, ``table1`` and ``deploy up`` fly the recommended setting by default."""

import dataclasses

import pytest
from typer.testing import CliRunner

from dronefl.cli import app
from dronefl.experiments.track import (
    RECOMMENDED,
    SETTING_FIELDS,
    SETTINGS,
    TrackConfig,
    setting_fields,
)


def test_every_setting_names_every_field_and_ours_is_the_config_defaults():
    defaults = {f.name: f.default for f in dataclasses.fields(TrackConfig)}

    assert all(set(values) == set(SETTING_FIELDS) for values in SETTINGS.values())
    assert SETTINGS["ours"] == {name: defaults[name] for name in SETTING_FIELDS}
    assert SETTINGS["recommended"].items() >= RECOMMENDED.items()
    assert SETTINGS["paper"] == {
        "preset": "paper", "labels": "filtered", "fusion": "paper", "label_drones": "all",
        "epochs": None, "noise_split": "adaptive", "correct_bias": False, "detected_only": False,
        "planner_distance": "next", "constant_speed_psd": None,
    }  # fmt: skip


def test_an_option_given_beside_a_setting_wins_also_a_false_flag():
    chosen = setting_fields("recommended", correct_bias=False, labels=None, epochs=10)

    assert chosen["correct_bias"] is False  # given: False wins over the setting's True
    assert chosen["labels"] == "smoothed"  # None: not given, the setting's
    assert chosen["epochs"] == 10
    assert chosen["detected_only"] is True
    with pytest.raises(ValueError, match="--setting: 'nope'"):
        setting_fields("nope")
    with pytest.raises(ValueError, match="stride"):
        setting_fields("ours", stride=3)


@pytest.fixture
def captured(monkeypatch):
    """The configs the commands would run, without running them."""
    import dronefl.deploy.launcher as launcher
    import dronefl.experiments.table1 as table1
    import dronefl.experiments.track as track

    seen = []

    def keep(config, *args, **kwargs):
        seen.append(config)
        raise SystemExit(0)

    monkeypatch.setattr(track, "run_episode", keep)
    monkeypatch.setattr(table1, "run_table1", keep)
    monkeypatch.setattr(launcher, "run_deploy", keep)
    return seen


def _run(*args: str) -> None:
    result = CliRunner().invoke(app, list(args))
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize("command", [["track"], ["table1"], ["deploy", "up"]])
def test_the_commands_fly_the_recommended_setting_by_default(command, captured, tmp_path):
    _run(*command, "--out", str(tmp_path / "out"), "--pretrained", str(tmp_path / "cache"))

    (config,) = captured
    for name, value in RECOMMENDED.items():
        assert getattr(config, name) == value, name


def test_track_flies_the_papers_setting_with_an_option_changed(captured, tmp_path):
    _run("track", "--setting", "paper", "--fusion", "robust", "--out", str(tmp_path / "o"),
         "--pretrained", str(tmp_path / "cache"))  # fmt: skip

    (config,) = captured
    assert (config.preset, config.labels, config.label_drones) == ("paper", "filtered", "all")
    assert config.fusion == "robust"  # given beside the setting
    assert config.epochs == 10  # the paper preset's E


def test_deploy_up_turns_a_recommended_flag_off(captured, tmp_path):
    _run("deploy", "up", "--no-detected-only", "--out", str(tmp_path / "o"),
         "--pretrained", str(tmp_path / "cache"))  # fmt: skip

    (config,) = captured
    assert config.detected_only is False and config.correct_bias is True
