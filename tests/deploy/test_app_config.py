"""The Flower app's declared run config holds every key the apps send (``flwr run -c`` refuses
an unknown key with "Invalid run configuration")."""

import tomllib
from pathlib import Path

from dronefl.deploy.cloud import CloudSettings
from dronefl.fl.records import FlSettings


def test_every_fl_setting_is_declared_in_the_app_config():
    pyproject = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    declared = set(pyproject["tool"]["flwr"]["app"]["config"])
    sent = set(FlSettings(run_dir="a", out_dir="b").to_run_config())
    sent |= set(CloudSettings(scenario="case1", model="m", out="o").to_run_config())
    assert sent - declared == set()
