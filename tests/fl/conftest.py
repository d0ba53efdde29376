"""FL test fixtures: a short recorded Case 1 run, and Flower's process identity, which its
``Message`` constructor needs outside a running app."""

import pytest
from flwr.supercore.task_identity import TaskIdentity

from dronefl.config import load_scenario
from dronefl.experiments.simulate import simulate


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: starts Flower's simulation engine (Ray, ~15 s)")


@pytest.fixture(autouse=True)
def task_identity():
    TaskIdentity.run_id, TaskIdentity.task_id, TaskIdentity.node_id = 1, 1, 1
    yield


@pytest.fixture(scope="session")
def case1_run(tmp_path_factory):
    """60 s of Case 1 (2 drones) in the crop field."""
    out = tmp_path_factory.mktemp("case1_run")
    simulate(load_scenario("case1"), duration=60.0, seed=1, out=out, progress=False, plot=False)
    return out
