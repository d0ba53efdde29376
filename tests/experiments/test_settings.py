"""Named closed-loop settings (``--setting``): what each sets, that options given beside it win,
and that ``track``, ``table1`` and ``deploy up`` fly the recommended setting by default."""

import dataclasses
from dataclasses import replace

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
        "planner_distance": "next", "constant_speed_psd": None, "random_walk_track_psd": None,
        "coverage_noise": False, "temporal_kernel": False, "pretrain_gaps": 0.0,
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


def test_the_planners_own_filter_is_for_random_walk_targets_only(tmp_path):
    from dronefl.config import load_scenario
    from dronefl.deploy.launcher import DeployConfig, _commands

    def config(case: str, **chosen: object) -> TrackConfig:
        fields = setting_fields("recommended", **chosen)
        return TrackConfig(scenario=load_scenario(case), out=tmp_path, **fields)

    # Case 2 (random walk): the recommended setting flies the planner on a q = 30 filter,
    # recorded as the episode's track_psd (the same as `--track-psd 30` beside one filter).
    case2 = config("case2")
    assert case2.planner_track_psd == 30.0
    assert case2.track_fusion_config().acceleration_psd == 30.0
    assert case2.fusion_config().acceleration_psd == 1.0  # the labels' filter
    assert case2.describe()["track_psd"] == 30.0 and "random_walk_track_psd" not in (
        case2.describe()
    )
    explicit = replace(case2, random_walk_track_psd=None, track_psd=30.0)
    assert explicit.settings() == case2.settings()
    # Cases 1 and 3 (constant speed) keep one filter: their episodes are those flown before.
    case3 = config("case3")
    assert case3.planner_track_psd is None
    assert case3.track_fusion_config() == case3.fusion_config()
    assert case3.settings() == replace(case3, random_walk_track_psd=None).settings()
    # --track-psd wins everywhere; a bad value is named.
    assert replace(case3, track_psd=3.0).planner_track_psd == 3.0
    assert config("case2", random_walk_track_psd=3.0).planner_track_psd == 3.0
    with pytest.raises(ValueError, match="--random-walk-track-psd"):
        config("case3", random_walk_track_psd=-1.0)
    # deploy up resolves it for the scenario and hands the cloud the q it flies.
    for case, expected in (("case2", 10.0), ("case3", None)):
        deploy = DeployConfig(scenario=case, out=tmp_path, random_walk_track_psd=10.0)
        cloud = _commands(deploy, load_scenario(case), tmp_path / "m.npz", None, tmp_path)["cloud"]
        given = float(cloud[cloud.index("--track-psd") + 1]) if "--track-psd" in cloud else None
        assert given == expected, case
    with pytest.raises(ValueError, match="--random-walk-track-psd"):
        DeployConfig(scenario="case2", out=tmp_path, random_walk_track_psd=0.0)


def test_coverage_noise_reaches_the_fusion_and_is_recorded_only_when_set(captured, tmp_path):
    from dronefl.config import load_scenario
    from dronefl.tracking.fusion import COVERAGE_NOISE_PROFILE

    _run("track", "--coverage-noise", "--out", str(tmp_path / "o"),
         "--pretrained", str(tmp_path / "cache"))  # fmt: skip

    (config,) = captured
    assert config.fusion_config().coverage_noise == COVERAGE_NOISE_PROFILE
    assert config.track_fusion_config().coverage_noise == COVERAGE_NOISE_PROFILE
    assert "coverage_noise" in config.describe()["fusion_config"]
    off = replace(config, coverage_noise=False)
    assert off.fusion_config().coverage_noise is None
    assert "coverage_noise" not in off.describe()["fusion_config"]  # as flown before it
    with pytest.raises(ValueError, match="--coverage-noise: needs --fusion robust"):
        TrackConfig(
            scenario=load_scenario("case2"), out=tmp_path, fusion="paper", coverage_noise=True
        )


def test_the_temporal_kernel_is_for_random_walk_targets_only(tmp_path):
    from dronefl.config import load_scenario
    from dronefl.deploy.launcher import DeployConfig, _commands
    from dronefl.tracking.fusion import TEMPORAL_KERNEL

    for case, kernel in (("case2", TEMPORAL_KERNEL), ("case3", None)):
        scenario = load_scenario(case)
        fields = setting_fields("recommended", temporal_kernel=True)
        config = TrackConfig(scenario=scenario, out=tmp_path, **fields)
        assert config.fusion_config().temporal_kernel == kernel
        assert config.track_fusion_config().temporal_kernel == kernel
        assert ("temporal_kernel" in config.describe()["fusion_config"]) == (kernel is not None)
        deploy = DeployConfig(scenario=case, out=tmp_path, temporal_kernel=True)
        cloud = _commands(deploy, scenario, tmp_path / "m.npz", None, tmp_path)["cloud"]
        assert ("--temporal-kernel" in cloud) == (kernel is not None)


def test_pretrain_gaps_reach_the_predictors_pretraining_not_the_image_model_s(tmp_path):
    from dronefl.config import load_scenario
    from dronefl.deploy.launcher import DeployConfig

    scenario = load_scenario("case2")
    for method, gaps in (("dronefl", 0.3), ("fixed", 0.3), ("centralized", 0.3)):
        config = TrackConfig(scenario, tmp_path, method=method, pretrain_gaps=gaps)
        assert config.pretrain_spec().detection_gaps == gaps
        assert config.describe()["pretrain_gaps"] == gaps
    image = TrackConfig(scenario, tmp_path, method="centralized-image", detector="yolo",
                        pretrain_gaps=0.3)  # fmt: skip
    assert image.pretrain_spec().detection_gaps == 0.0
    # None: no key, as every episode flown before the option.
    assert "pretrain_gaps" not in TrackConfig(scenario, tmp_path).describe()
    assert DeployConfig(scenario="case2", out=tmp_path, pretrain_gaps=0.3).pretrain_gaps == 0.3
    auto = TrackConfig(scenario, tmp_path, pretrain_gaps="auto")
    assert auto.describe()["pretrain_gaps"] == "auto"
    for bad in (-0.1, 1.5, "often"):
        with pytest.raises(ValueError, match="--pretrain-gaps: must be .auto. or in"):
            TrackConfig(scenario, tmp_path, pretrain_gaps=bad)
        with pytest.raises(ValueError, match="--pretrain-gaps: must be .auto. or in"):
            DeployConfig(scenario="case2", out=tmp_path, pretrain_gaps=bad)
