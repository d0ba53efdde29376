"""Fixtures of the deployment tests."""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import pytest
from deploy_helpers import MARK, ROOT


@pytest.fixture
def run_env(tmp_path: Path) -> dict[str, str]:
    """Environment for a deployment command: this checkout first, caches in ``tmp_path``,
    and a fresh :data:`MARK`."""
    env = dict(os.environ)
    env.pop("DRONEFL_DEPLOY_OWNER", None)
    env.update(
        {
            "PYTHONPATH": str(ROOT),
            MARK: uuid.uuid4().hex,
            "FLWR_TELEMETRY_ENABLED": "0",
            "MPLBACKEND": "Agg",
            "YOLO_OFFLINE": "1",
            "HOME": str(tmp_path / "home"),
        }
    )
    return env


@pytest.fixture(scope="session")
def quick_pretrained(tmp_path_factory) -> Path:
    """A DroneFL model for case1 trained for a few seconds on 60 s of crop field, cached
    where ``--pretrained`` looks (deployment tests check the plumbing, not the accuracy)."""
    import torch

    from dronefl.config import load_scenario
    from dronefl.experiments.pretrain import PretrainSpec
    from dronefl.experiments.simulate import simulate
    from dronefl.fl.checkpoint import Checkpoint, save_checkpoint
    from dronefl.logs import load_run
    from dronefl.models.model import build_model, predictor_config
    from dronefl.models.train import TrainConfig, train_local
    from dronefl.models.windows import WindowSet, WindowSpec, build_windows, ground_truth_labels

    folder = tmp_path_factory.mktemp("pretrained")
    data = folder / "data"
    simulate(
        load_scenario("case1"), environment="crop_field", duration=60.0, seed=5, out=data,
        progress=False, plot=False,
    )  # fmt: skip
    logs, truth = load_run(data)
    spec = WindowSpec(10, 1, relative=True, stride=2)
    windows = WindowSet.concat(
        [build_windows(log, ground_truth_labels(log, truth), spec) for log in logs.values()]
    )
    model = build_model(predictor_config("dronefl", 10, 1), seed=0)
    torch.set_num_threads(1)
    train_local(model, windows, TrainConfig(epochs=5, seed=0))
    settings = PretrainSpec(load_scenario("case1"), "dronefl").settings(folder)
    save_checkpoint(
        settings.checkpoint_path,
        settings.history_path,
        Checkpoint("dronefl", settings.rounds, model.state_dict(), []),
    )
    return folder
