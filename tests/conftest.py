"""Test-wide settings (headless plotting, tool caches inside a temp dir, no telemetry) and the
shared fixture of a quickly pretrained Case 1 model."""

import os
import tempfile

import pytest

_CACHE = tempfile.mkdtemp(prefix="dronefl-test-cache-")
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("MPLCONFIGDIR", os.path.join(_CACHE, "matplotlib"))
os.environ.setdefault("FLWR_HOME", os.path.join(_CACHE, "flwr"))
os.environ.setdefault("FLWR_TELEMETRY_ENABLED", "0")
os.environ.setdefault("YOLO_OFFLINE", "1")
os.environ.setdefault("YOLO_CONFIG_DIR", os.path.join(_CACHE, "ultralytics"))
os.environ.setdefault("RAY_DEDUP_LOGS", "0")


@pytest.fixture(scope="session")
def quick_pretrained(tmp_path_factory):
    """A DroneFL model for Case 1 trained for ~6 s on 120 s of crop field (held-out error
    ~2.5 m^2, good enough for the closed loop to keep its targets in view), cached where the
    closed loop and ``deploy up --pretrained`` look for pretrained weights."""
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
        load_scenario("case1"),
        environment="crop_field",
        duration=120.0,
        seed=5,
        out=data,
        progress=False,
        plot=False,
    )
    logs, truth = load_run(data)
    spec = WindowSpec(10, 1, relative=True, stride=2)
    windows = WindowSet.concat(
        [build_windows(log, ground_truth_labels(log, truth), spec) for log in logs.values()]
    )
    model = build_model(predictor_config("dronefl", 10, 1), seed=0)
    torch.set_num_threads(1)
    train_local(model, windows, TrainConfig(epochs=20, batch_size=32, seed=0))
    settings = PretrainSpec(load_scenario("case1"), "dronefl").settings(folder)
    save_checkpoint(
        settings.checkpoint_path,
        settings.history_path,
        Checkpoint("dronefl", settings.rounds, model.state_dict(), []),
    )
    return folder
