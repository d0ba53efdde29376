"""The Flower app's declared run config holds every key the apps send (``flwr run -c`` refuses
an unknown key with "Invalid run configuration"); the staged copy of the app that ``flwr run``
builds its FAB from holds every file the app needs."""

import tomllib
from dataclasses import replace
from pathlib import Path

import pytest
from flwr.cli.build import get_filtered_fab_paths
from flwr.cli.utils import collect_files

from dronefl.deploy import CloudError
from dronefl.deploy.cloud import CloudSettings
from dronefl.deploy.flower import stage_app
from dronefl.fl.records import FlSettings


def test_every_fl_setting_is_declared_in_the_app_config():
    pyproject = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    declared = set(pyproject["tool"]["flwr"]["app"]["config"])
    sent = set(FlSettings(run_dir="a", out_dir="b").to_run_config())
    sent |= set(CloudSettings(scenario="case1", model="m", out="o").to_run_config())
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


def test_cloud_settings_survive_the_run_config():
    settings = CloudSettings(
        scenario="case2", model="m", out="o", round_timeout=12.5, deshrink_labels=True,
        constant_speed_psd=1e-3,
    )  # fmt: skip
    assert CloudSettings.from_run_config(settings.to_run_config()) == settings
    # A second filter's q travels as a float, its absence as 0 (TOML has no null).
    for track_psd, sent in ((None, 0.0), (10.0, 10.0)):
        second = replace(settings, track_psd=track_psd)
        assert second.to_run_config()["deploy-track-psd"] == sent
        assert CloudSettings.from_run_config(second.to_run_config()) == second
    # A flag given as text is refused by name ("false" would be true to bool()).
    as_text = {**settings.to_run_config(), "deploy-deshrink-labels": "false"}
    with pytest.raises(CloudError, match="'deploy-deshrink-labels' must be a bool"):
        CloudSettings.from_run_config(as_text)
