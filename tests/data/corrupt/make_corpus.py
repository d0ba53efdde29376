"""Write the corrupt-file corpus beside this script (run once; the files are committed).

    PYTHONPATH=. python tests/data/corrupt/make_corpus.py

One folder per loader, one file per way of being broken: ``empty``, ``truncated`` (the first
half of a valid file), ``wrong_format`` (another kind of file), ``wrong_version``, ``nan`` (a
well-formed file holding NaN where a number must be finite) and ``wrong_shape``. ``missing``
needs no file. Each folder also holds ``valid`` (except for the ONNX model, whose valid case is
the shipped detector), which loads, so that a test would notice a loader that rejects
everything. Every file is a few hundred bytes to a few kB.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import torch
import yaml
from onnx import TensorProto, helper

from dronefl.config import load_scenario
from dronefl.experiments.simulate import scenario_dict
from dronefl.fl.checkpoint import Checkpoint, save_checkpoint
from dronefl.fl.records import RoundRecord
from dronefl.logs import GroundTruth, OnboardLog, PseudoLabels

HERE = Path(__file__).resolve().parent
T, N, M = 4, 2, 2  # steps, targets, drones


def onboard(**change) -> OnboardLog:
    fields = dict(
        drone_id=1,
        altitude=30.0,
        t=np.arange(T) * 0.2,
        odometry=np.zeros((T, 12), np.float32),
        target_ids=np.array([1, 2], np.int32),
        assigned=np.array([True, False]),
        boxes=np.full((T, N, 4), 0.5, np.float32),
        detected=np.ones((T, N), bool),
        confidence=np.full((T, N), 0.9, np.float32),
        meta={"scenario": "corpus"},
    )
    return OnboardLog(**{**fields, **change})


def truth(**change) -> GroundTruth:
    fields = dict(
        t=np.arange(T) * 0.2,
        target_ids=np.array([1, 2]),
        target_position=np.zeros((T, N, 2)),
        target_velocity=np.zeros((T, N, 2)),
        target_heading=np.zeros((T, N)),
        drone_ids=np.array([1, 2]),
        drone_position=np.zeros((T, M, 2)),
        drone_velocity=np.zeros((T, M, 2)),
        drone_altitude=np.array([30.0, 20.0]),
        meta={"scenario": "corpus"},
    )
    return GroundTruth(**{**fields, **change})


def labels(**change) -> PseudoLabels:
    fields = dict(t=np.arange(T) * 0.2, target_ids=np.array([1, 2]), position=np.zeros((T, N, 2)))
    return PseudoLabels(**{**fields, **change})


def npz_versions(folder: Path, make, nan: dict, shape: dict, other: Path) -> None:
    """valid / truncated / wrong_format / wrong_version / nan / wrong_shape .npz files."""
    valid = make().save(folder / "valid.npz")
    data = valid.read_bytes()
    (folder / "truncated.npz").write_bytes(data[: len(data) // 2])
    (folder / "wrong_format.npz").write_bytes(other.read_bytes())
    with np.load(valid) as npz:
        arrays = {k: npz[k] for k in npz.files}
    np.savez_compressed(folder / "wrong_version.npz", **{**arrays, "version": np.array(99)})
    make(**nan).save(folder / "nan.npz")
    make(**shape).save(folder / "wrong_shape.npz")


def checkpoints(folder: Path) -> None:
    state = {"layer.weight": torch.ones(2, 3), "layer.bias": torch.zeros(2)}
    history = [RoundRecord(1, {1: 1.0})]

    def save(name: str, **tensors: torch.Tensor) -> Path:
        path = folder / f"{name}.npz"
        save_checkpoint(path, folder / "history.json", Checkpoint("fedavg", 1, tensors, history))
        return path

    data = save("valid", **state).read_bytes()
    (folder / "truncated.npz").write_bytes(data[: len(data) // 2])
    (folder / "wrong_format.npz").write_bytes((HERE / "onboard_log" / "valid.npz").read_bytes())
    with np.load(folder / "valid.npz") as npz:
        arrays = {k: npz[k] for k in npz.files}
    np.savez_compressed(
        folder / "wrong_version.npz", **{**arrays, "format": np.array("dronefl.fl_checkpoint.v0")}
    )
    save("nan", **{**state, "layer.bias": torch.tensor([0.0, float("nan")])})
    save("wrong_shape", **{**state, "layer.weight": torch.ones(3, 2)})


def texts(folder: Path, suffix: str, files: dict[str, str]) -> None:
    for name, text in files.items():
        (folder / f"{name}{suffix}").write_text(text)


def histories(folder: Path) -> None:
    valid = json.dumps([RoundRecord(1, {1: 1.0}).to_json(), RoundRecord(2, {1: 0.5}).to_json()])
    texts(folder, ".json", {
        "valid": valid,
        "empty": "",
        "truncated": valid[: len(valid) // 2],
        "wrong_format": json.dumps({"round": 1}),
        "wrong_version": json.dumps([{"epoch": 1}, {"epoch": 2}]),  # not round entries
        "nan": json.dumps([{"round": float("nan")}, {"round": 2}]),
        "wrong_shape": json.dumps([{"round": 1}]),  # one round where the checkpoint says two
    })  # fmt: skip


def results(folder: Path) -> None:
    seed = {
        "seed": 0,
        "final_test_mse": 1.5,
        "final_test_mse_per_drone": {"1": 1.5},
        "mean_test_mse": [2.0, 1.5],
        "bytes_down_per_round": [10, 10],
        "bytes_up_per_round": [10, 10],
        "rejected": {},
        "wall_seconds": 1.0,
    }
    method = {"model": "dronefl", "parameters": 10, "training": "federated", "per_seed": [seed]}
    head = {
        "scenario": "case1",
        "setting": "recommended",
        "setting_digest": "0123456789ab",
        "rounds": 2,
        "duration_s": 60.0,
        "stride": 10,
    }
    valid = json.dumps({**head, "methods": {"fedavg": method}})
    texts(folder, ".json", {
        "valid": valid,
        "empty": "",
        "truncated": valid[: len(valid) // 2],
        "wrong_format": json.dumps([1, 2, 3]),
        "wrong_version": json.dumps({"case": 1, "method_results": {}}),  # the old layout
        "nan": json.dumps({**head, "rounds": float("nan"), "methods": {"fedavg": method}}),
        "wrong_shape": json.dumps({**head, "methods": [method]}),
    })  # fmt: skip


def scenes(folder: Path) -> None:
    record = {
        "image": "000000.jpg",
        "environment": "crop_field",
        "camera_position": [80.0, 60.0, 30.0],
        "yaw": 0.0,
        "targets": [[1, 80.0, 60.0, 0.0]],
        "labels": [[1, 0.5, 0.5, 0.1, 0.05, 1.0]],
    }
    valid = json.dumps(record)
    texts(folder, ".jsonl", {
        "valid": valid + "\n" + json.dumps({**record, "image": "000001.jpg"}) + "\n",
        "empty": "",
        "truncated": valid[: len(valid) // 2] + "\n",
        "wrong_format": "image,environment\n000000.jpg,crop_field\n",
        "wrong_version": json.dumps({**record, "labels": {"1": [0.5, 0.5, 0.1, 0.05]}}) + "\n",
        "nan": json.dumps({**record, "labels": [[1, float("nan"), 0.5, 0.1, 0.05, 1.0]]}) + "\n",
        "wrong_shape": json.dumps({**record, "labels": [[1, 0.5, 0.5], [0.1, 0.05, 1.0]]}) + "\n",
    })  # fmt: skip


def onnx_models(folder: Path) -> None:
    def model(weight: np.ndarray, input_shape: list[int], ir_version: int = 8) -> bytes:
        x = helper.make_tensor_value_info("images", TensorProto.FLOAT, input_shape)
        y = helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(weight.shape))
        w = helper.make_tensor("w", TensorProto.FLOAT, weight.shape, weight.ravel().tolist())
        graph = helper.make_graph(
            [helper.make_node("Identity", ["w"], ["output0"])], "corpus", [x], [y], [w]
        )
        onnx_model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
        onnx_model.ir_version = ir_version
        return onnx_model.SerializeToString()

    good_shape = np.zeros((1, 6, 10), np.float32)  # (1, 4 + 2 classes, 10 candidates)
    valid = model(good_shape, [1, 3, 32, 32])
    files = {
        "empty": b"",
        "truncated": valid[: len(valid) // 2],
        "wrong_format": b"\x89PNG\r\n\x1a\n not a model",
        "wrong_version": model(good_shape, [1, 3, 32, 32], ir_version=99),
        "nan": model(np.full((1, 6, 10), np.nan, np.float32), [1, 3, 32, 32]),
        "wrong_shape": model(np.zeros((1, 3), np.float32), [1, 3]),
    }
    for name, data in files.items():
        (folder / f"{name}.onnx").write_bytes(data)
    onnx.checker.check_model(onnx.load_from_string(valid))


def scenarios(folder: Path) -> None:
    valid = yaml.safe_dump(scenario_dict(load_scenario("case1")), sort_keys=False)
    raw = yaml.safe_load(valid)
    nan = json.loads(json.dumps(raw))
    nan["targets"][0]["speed"] = float("nan")
    shape = json.loads(json.dumps(raw))
    shape["drones"][0]["start"] = [10.0, 20.0, 30.0]
    texts(folder, ".yaml", {
        "valid": valid,
        "empty": "",
        "truncated": valid[: len(valid) // 2].rsplit("\n", 1)[0] + "\n",
        "wrong_format": json.dumps([1, 2, 3]),
        "wrong_version": valid.replace("targets:", "vehicles:", 1),
        "nan": yaml.safe_dump(nan, sort_keys=False),
        "wrong_shape": yaml.safe_dump(shape, sort_keys=False),
    })  # fmt: skip


def main() -> None:
    folders = {
        name: HERE / name
        for name in ("onboard_log", "ground_truth", "pseudo_labels", "checkpoint", "history",
                     "results", "scenes", "onnx", "scenario")
    }  # fmt: skip
    for folder in folders.values():
        folder.mkdir(exist_ok=True)
    npz_versions(
        folders["onboard_log"],
        onboard,
        nan={"odometry": np.full((T, 12), np.nan, np.float32)},
        shape={"boxes": np.zeros((T, N, 3), np.float32)},
        other=truth().save(folders["ground_truth"] / "valid.npz"),
    )
    npz_versions(
        folders["ground_truth"],
        truth,
        nan={"target_position": np.full((T, N, 2), np.nan)},
        shape={"drone_altitude": np.array([30.0])},
        other=folders["onboard_log"] / "valid.npz",
    )
    npz_versions(
        folders["pseudo_labels"],
        labels,
        nan={"t": np.array([0.0, np.nan, 0.4, 0.6])},
        shape={"position": np.zeros((T, N, 3))},
        other=folders["onboard_log"] / "valid.npz",
    )
    checkpoints(folders["checkpoint"])
    histories(folders["history"])
    results(folders["results"])
    scenes(folders["scenes"])
    onnx_models(folders["onnx"])
    scenarios(folders["scenario"])
    for name in ("onboard_log", "ground_truth", "pseudo_labels", "checkpoint"):
        (folders[name] / "empty.npz").write_bytes(b"")


if __name__ == "__main__":
    main()
