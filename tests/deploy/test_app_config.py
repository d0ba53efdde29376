"""The Flower app's declared run config holds every key the apps send (``flwr run -c`` refuses
an unknown key with "Invalid run configuration"); the staged copy of the app that ``flwr run``
builds its FAB from holds every file the app needs."""

import tomllib
from pathlib import Path

import pytest
from flwr.cli.build import get_filtered_fab_paths
from flwr.cli.utils import collect_files

from dronefl.deploy import CloudError
from dronefl.deploy.cloud import CloudSettings
from dronefl.deploy.flower import stage_app
from dronefl.fl.records import FlSettings
from dronefl.settings import Setting


def test_every_fl_setting_is_declared_in_the_app_config():
    pyproject = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    declared = set(pyproject["tool"]["flwr"]["app"]["config"])
    sent = set(FlSettings(run_dir="a", out_dir="b").to_run_config())
    sent |= set(_cloud().to_run_config())
    assert sent - declared == set()


def test_the_staged_app_is_the_package_and_its_scenarios(tmp_path):
    root = Path(__file__).parents[2]
    (tmp_path / "app").mkdir()
    (tmp_path / "app" / "stale.py").write_text("")  # a previous run's copy is replaced
    staged = stage_app(tmp_path / "app")
    config = tomllib.loads((staged / "pyproject.toml").read_text())
    fab = set(get_filtered_fab_paths(collect_files(staged), config))
    package = {p.relative_to(root).as_posix() for p in (root / "dronefl").rglob("*.py")}
    scenarios = {
        p.relative_to(root).as_posix() for p in (root / "dronefl" / "scenarios").glob("*.yaml")
    }
    assert package and scenarios
    assert fab == package | scenarios  # pyproject.toml is added to every FAB apart
    assert (staged / "dronefl/deploy/cloud.py").read_bytes() == (
        root / "dronefl/deploy/cloud.py"
    ).read_bytes()


def _cloud(**changed) -> CloudSettings:
    values = {
        "scenario": "case2", "model": "m", "out": "o", "setting": Setting.load().to_toml(),
        "method": "dronefl", "duration": 60.0, "deadline_ms": 150.0, "listen": "127.0.0.1:1",
        "connect": "127.0.0.1:2", "tls_dir": "", "start_timeout": 30.0,
    }  # fmt: skip
    return CloudSettings(**{**values, **changed})


def test_cloud_settings_survive_the_run_config_with_the_setting_whole():
    settings = _cloud(round_timeout=12.5)
    assert CloudSettings.from_run_config(settings.to_run_config()) == settings
    paper = _cloud(setting=Setting.load("paper").to_toml())
    assert CloudSettings.from_run_config(paper.to_run_config()).resolved == Setting.load("paper")
    with pytest.raises(CloudError, match="run config: setting deployed"):
        _cloud(setting="[fusion]\nmethod = 'kalman'\n")
    with pytest.raises(ValueError, match="--method: 'centralized' is not one of"):
        _cloud(method="centralized")
