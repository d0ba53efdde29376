"""One typed setting: the named files load, a user's file and ``--set`` change fields, every bad
value is named, the digest names the content, and every command and the Python API fly the
recommended setting by default."""

import dataclasses
import tomllib

import pytest
from typer.testing import CliRunner

from dronefl.cli import app
from dronefl.settings import (
    ADAIN_SITES,
    BOX_SIZES,
    DISTANCE_POINTS,
    FUSION_METHODS,
    LABEL_DRONES,
    LABEL_SOURCES,
    OPTIMIZERS,
    STYLE_INITS,
    Setting,
    SettingError,
    named_settings,
    setting_fields,
)


def test_the_named_settings_give_every_field_and_differ_where_the_paper_does():
    assert named_settings() == ("paper", "recommended")
    recommended, paper = Setting.load("recommended"), Setting.load("paper")
    assert Setting.load() == recommended and recommended.name == "recommended"
    for setting in (recommended, paper):
        assert set(setting.to_dict()) == set(setting_fields())
    assert (paper.training.optimizer, paper.training.lr, paper.learning.epochs) == (
        "adam",
        1e-3,
        10,
    )
    assert (paper.learning.labels, paper.fusion.method) == ("filtered", "paper")
    assert (recommended.learning.epochs, recommended.drone.detected_only) == (1, True)
    assert paper.fusion.random_walk_planner_psd is None
    assert (
        paper.pretraining.detection_gaps == 0.0 and recommended.pretraining.detection_gaps == "auto"
    )


def test_the_choices_are_the_registries_names():
    from dronefl.models.model import PredictorConfig
    from dronefl.models.train import TrainConfig
    from dronefl.planning import PlannerConfig
    from dronefl.tracking import labels, methods

    assert set(FUSION_METHODS) == set(methods.FUSION_METHODS)
    assert set(LABEL_SOURCES) == set(labels.LABEL_SOURCES)
    assert LABEL_DRONES == labels.LABEL_DRONES
    for optimizer in OPTIMIZERS:
        TrainConfig(optimizer=optimizer)
    for distance in DISTANCE_POINTS:
        PlannerConfig(distance_at=distance)
    for sites in ADAIN_SITES:
        PredictorConfig(adain_sites=(sites,))
    for init in STYLE_INITS:
        PredictorConfig(head_style_init=init)
    for box in BOX_SIZES:
        PredictorConfig(box_size=box)


def test_set_overrides_one_field_and_the_digest_follows_the_content():
    base = Setting.load()
    changed = Setting.load("recommended", ["fusion.temporal_kernel=false", "learning.period=50"])
    assert changed.fusion.temporal_kernel is False and changed.learning.period == 50.0
    assert changed.name == "recommended + fusion.temporal_kernel=false learning.period=50"
    assert changed.digest() != base.digest()
    # The digest is the content's, whatever the name or the way there.
    same = base.with_values(fusion={"temporal_kernel": False}, learning={"period": 50.0})
    assert same == changed and same.digest() == changed.digest()
    assert base.override(["fusion.temporal_kernel=false", "learning.period=50"]) == changed
    back = Setting.load("recommended", ["fusion.random_walk_planner_psd=none"])
    assert back.fusion.random_walk_planner_psd is None
    assert (
        Setting.load("recommended", ["pretraining.detection_gaps=0.3"]).pretraining.detection_gaps
        == 0.3
    )
    assert Setting.load("recommended", ['model.adain_sites=["encoder"]']).model.adain_sites == (
        "encoder",
    )


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["fusion.method=kalman"], r"fusion.method: 'kalman' is not one of robust, paper"),
        (["fusion.gate=3"], r"fusion.gate: unknown field"),
        (["radio.loss=0.1"], r"unknown section 'radio'"),
        (["fusion.method"], r"expected section.field=value"),
        (["training.lr=nan"], r"training.lr: must be finite"),
        (["training.lr=inf"], r"training.lr: must be finite"),
        (["training.lr=0"], r"training.lr: must be > 0"),
        (["learning.period=1e300"], r"learning.period: must be in"),
        (["training.epochs=1.5"], r"training.epochs: must be an integer"),
        (["drone.detected_only=1"], r"drone.detected_only: must be true or false"),
        (["pretraining.detection_gaps=often"], r"detection_gaps: must be 'auto' or in"),
        (["pretraining.detection_gaps=1.5"], r"detection_gaps: must be 'auto' or in"),
        (['model.adain_sites=["decoder"]'], r"model.adain_sites: must be distinct names"),
        (["training.optimizer=adam"], r"'scaffold' needs training.optimizer 'sgd'"),
        (["fusion.method=paper"], r"drone.noise_reports: the paper fusion cannot use them"),
    ],
)
def test_a_bad_override_is_named(overrides, message):
    with pytest.raises(SettingError, match=message):
        Setting.load("recommended", overrides)


def test_a_users_file_starts_from_a_base_and_is_checked_like_a_named_one(tmp_path):
    mine = tmp_path / "mine.toml"
    mine.write_text('base = "paper"\n\n[learning]\nperiod = 50.0\n')
    setting = Setting.load(str(mine))
    assert setting.learning.period == 50.0 and setting.training == Setting.load("paper").training
    assert Setting.from_toml(setting.to_toml()) == setting  # a whole file reads back
    full = tmp_path / "full.toml"
    full.write_text(setting.to_toml())
    assert Setting.load(str(full)) == setting
    for text, message in (
        ('base = "paper"\n[fusion]\nmethod = 3\n', r"fusion.method: must be a name, got 3"),
        ("[model]\npast_steps = 10\n", r"model.adain_sites: missing"),
        ('base = "paper"\n[radio]\nloss = 0.1\n', r"unknown section 'radio'"),
        ("not toml = = 1", r"not a readable TOML file"),
        (f'base = "{tmp_path / "loop.toml"}"\n', r"bases form a loop"),
    ):
        bad = tmp_path / "loop.toml"
        bad.write_text(text)
        with pytest.raises(SettingError, match=message) as raised:
            Setting.load(str(bad))
        assert str(bad) in str(raised.value)  # the file is named
    with pytest.raises(SettingError, match="no such file, nor a named setting"):
        Setting.load("fastest")


def test_setting_show_prints_every_field_with_its_doc_and_a_file_that_loads_back():
    shown = CliRunner().invoke(app, ["setting", "show", "paper", "--set", "learning.period=50"])
    assert shown.exit_code == 0, shown.output
    for section, names in setting_fields().items():
        assert f"[{section}]" in shown.output
        for name in names:
            assert f"\n{name} = " in shown.output
    assert (
        "learning.period=50" in shown.output and "seconds of flight between rounds" in shown.output
    )
    toml = CliRunner().invoke(app, ["setting", "show", "recommended", "--toml"])
    assert Setting.from_dict(tomllib.loads(toml.output)) == Setting.load()
    bad = CliRunner().invoke(app, ["setting", "show", "--set", "fusion.method=kalman"])
    assert bad.exit_code == 2 and "fusion.method" in bad.output


@pytest.fixture
def captured(monkeypatch):
    """The configs the commands would run, without running them."""
    import dronefl.deploy.launcher as launcher
    import dronefl.experiments.prepare as prepare
    import dronefl.experiments.table1 as table1
    import dronefl.experiments.track as track

    seen = []

    def keep(config, *args, **kwargs):
        seen.append(config)
        raise SystemExit(0)

    monkeypatch.setattr(track, "run_episode", keep)
    monkeypatch.setattr(table1, "run_table1", keep)
    monkeypatch.setattr(launcher, "run_deploy", keep)
    stand_in = prepare.Prepared(spec=dataclasses.make_dataclass("Spec", ["model"])(None), state={})
    monkeypatch.setattr(prepare, "prepare", lambda *a, **k: stand_in)
    return seen


def _run(*args: str) -> None:
    result = CliRunner().invoke(app, list(args))
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize("command", [["track"], ["table1"], ["deploy", "up"]])
def test_the_commands_fly_the_recommended_setting_by_default(command, captured, tmp_path):
    _run(*command, "--out", str(tmp_path / "out"), "--pretrained", str(tmp_path / "cache"))

    (config,) = captured
    assert config.setting == Setting.load("recommended")


def test_the_python_default_is_the_command_s_default(captured, tmp_path):
    """``TrackConfig(scenario, out)`` flies the same episode as ``dronefl track`` with no
    option: one default, in the setting files, for both."""
    from dronefl.config import load_scenario
    from dronefl.experiments.track import TrackConfig

    _run("track", "--out", str(tmp_path / "o"), "--pretrained", str(tmp_path / "cache"))

    (command,) = captured
    python = TrackConfig(load_scenario("case2"), tmp_path / "o")
    assert python.identity() == command.identity()
    assert python.setting == command.setting == Setting.load()


def test_track_flies_the_papers_setting_with_a_field_changed(captured, tmp_path):
    _run("track", "--setting", "paper", "--set", "fusion.method=robust", "--out",
         str(tmp_path / "o"), "--pretrained", str(tmp_path / "cache"))  # fmt: skip

    (config,) = captured
    assert config.setting.fusion.method == "robust"  # given beside the setting
    assert config.setting.learning == Setting.load("paper").learning


def test_deploy_up_turns_a_recommended_flag_off(captured, tmp_path):
    _run("deploy", "up", "--set", "drone.detected_only=false", "--out", str(tmp_path / "o"),
         "--pretrained", str(tmp_path / "cache"))  # fmt: skip

    (config,) = captured
    assert config.setting.drone.detected_only is False and config.setting.drone.correct_bias


def test_the_deployed_processes_receive_the_setting_whole(tmp_path):
    from dronefl.config import load_scenario
    from dronefl.deploy.launcher import SETTING_FILE, DeployConfig, _commands

    setting = Setting.load("recommended", ["learning.period=25"])
    deploy = DeployConfig(scenario="case2", out=tmp_path, setting=setting)
    commands = _commands(deploy, load_scenario("case2"), tmp_path / "m.npz", None, tmp_path)
    for role in ("cloud", "drone-1", "drone-3"):
        line = commands[role]
        assert line[line.index("--setting") + 1] == str(tmp_path / SETTING_FILE)
    assert "--setting" not in commands["world"]
    assert not any(
        flag.startswith("--temporal") or flag == "--fl-period" for flag in commands["cloud"]
    )
    with pytest.raises(
        ValueError, match="learning.labels: a deployed cloud does not know the truth"
    ):
        DeployConfig(
            scenario="case2", out=tmp_path,
            setting=Setting.load("recommended", ["learning.labels=ground_truth"]),
        )  # fmt: skip


def test_the_pretraining_gaps_reach_the_predictors_pretraining_not_the_image_model_s(tmp_path):
    from dronefl.config import load_scenario
    from dronefl.experiments.gap_choice import resolve_gaps
    from dronefl.experiments.pretrain import PretrainSpec

    scenario = load_scenario("case2")
    setting = Setting.load("recommended", ["pretraining.detection_gaps=0.3"])
    for kind in ("dronefl", "centralized"):
        assert resolve_gaps(PretrainSpec(scenario, setting, kind), tmp_path).detection_gaps == 0.3
    image = PretrainSpec(scenario, setting, "image")
    assert resolve_gaps(image, tmp_path).detection_gaps == 0.0
