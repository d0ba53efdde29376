"""The diagnostic tool's in-process server optimisers follow Flower's FedAdam and FedYogi."""

import argparse
import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch
from flwr.app import Array, ArrayRecord, Message, RecordDict
from flwr.serverapp.strategy import FedAdam, FedYogi

from dronefl.fl.records import ClientReport

TOOL = Path(__file__).resolve().parents[2] / "benchmarks" / "fl_diagnose.py"


def _tool():
    spec = importlib.util.spec_from_file_location("fl_diagnose", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(("name", "strategy"), [("adam", FedAdam), ("yogi", FedYogi)])
def test_server_step_equals_flowers_strategy_over_three_rounds(name, strategy):
    # Prepare: two drones with 1 and 3 windows send noisy copies of the global weights.
    rng = np.random.default_rng(0)
    flower, tool = strategy(eta=0.05), _tool()
    args = argparse.Namespace(server_opt=name, server_lr=0.05)
    moments: dict = {"m": {}, "v": {}}
    w = rng.normal(size=7)
    for server_round in (1, 2, 3):
        local = [w + rng.normal(scale=0.1, size=7) for _ in range(2)]
        replies = [
            Message(
                content=RecordDict(
                    {
                        "arrays": ArrayRecord({"w": Array(x)}),
                        "metrics": ClientReport(d, n, 1.0).to_metrics(),
                    }
                ),
                dst_node_id=0,
                message_type="train",
            )
            for d, (x, n) in enumerate(zip(local, (1, 3), strict=True), start=1)
        ]
        # Execute: Flower's strategy and the tool's step from the same weights.
        flower.current_arrays = {"w": w.copy()}
        arrays, _ = flower.aggregate_train(server_round, replies)
        average = {"w": torch.tensor((local[0] + 3 * local[1]) / 4)}
        ours = tool.server_step(args, server_round, {"w": torch.tensor(w)}, average, moments)
        # Verify
        np.testing.assert_allclose(ours["w"].numpy(), arrays["w"].numpy(), rtol=1e-12, atol=1e-15)
        assert not np.allclose(arrays["w"].numpy(), w)  # the step moved the weights
        w = arrays["w"].numpy()
