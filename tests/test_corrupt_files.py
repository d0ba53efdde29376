"""Every loader x every way a file can be broken (tests/data/corrupt/, made by its
make_corpus.py) -> one error of the loader's type whose message names the file; the valid file
of each corpus folder loads."""

from pathlib import Path

import pytest
import torch

from dronefl.config import ScenarioError, load_scenario
from dronefl.fl.checkpoint import CheckpointError, load_checkpoint, load_history
from dronefl.logs import GroundTruth, LogError, OnboardLog, PseudoLabels
from dronefl.perception.dataset import read_scenes
from dronefl.perception.yolo import YoloDetector, shipped_detector_path
from dronefl.results.fl import OfflineResults

CORPUS = Path(__file__).parent / "data" / "corrupt"
#: The model the corpus checkpoints were saved from.
LIKE = {"layer.weight": torch.ones(2, 3), "layer.bias": torch.zeros(2)}

#: loader name -> (load function, error it raises, file suffix)
LOADERS = {
    "onboard_log": (OnboardLog.load, LogError, ".npz"),
    "ground_truth": (GroundTruth.load, LogError, ".npz"),
    "pseudo_labels": (PseudoLabels.load, LogError, ".npz"),
    "checkpoint": (
        lambda p: load_checkpoint(p, p.parent / "history.json", "fedavg", like=LIKE),
        CheckpointError,
        ".npz",
    ),
    "history": (lambda p: load_history(p, server_round=2), CheckpointError, ".json"),
    "results": (OfflineResults.load, CheckpointError, ".json"),
    "scenes": (read_scenes, ValueError, ".jsonl"),
    "onnx": (YoloDetector, ValueError, ".onnx"),
    "scenario": (load_scenario, ScenarioError, ".yaml"),
}
CASES = ("missing", "empty", "truncated", "wrong_format", "wrong_version", "nan", "wrong_shape")
#: A fresh run folder has no results yet: a missing results.json is not an error.
NOT_ERRORS = {("results", "missing")}
BROKEN = [
    (loader, case) for loader in LOADERS for case in CASES if (loader, case) not in NOT_ERRORS
]


@pytest.mark.parametrize(("loader", "case"), BROKEN)
def test_a_broken_file_gives_one_error_naming_it(loader, case):
    load, error, suffix = LOADERS[loader]
    path = CORPUS / loader / f"{case}{suffix}"
    assert path.exists() == (case != "missing")
    # A missing file may also be reported as FileNotFoundError (an OSError, not a ValueError).
    with pytest.raises((error, FileNotFoundError)) as caught:
        load(path)
    assert str(path) in str(caught.value)
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize("loader", list(LOADERS))
def test_the_valid_file_of_each_corpus_folder_loads(loader):
    load, _, suffix = LOADERS[loader]
    # The valid ONNX model is the shipped detector (10 MB, so not copied into the corpus).
    path = shipped_detector_path() if loader == "onnx" else CORPUS / loader / f"valid{suffix}"
    assert load(path) is not None


def test_the_corpus_counts():
    files = [p for p in CORPUS.rglob("*") if p.is_file() and p.stem in CASES]
    assert len(files) == len(LOADERS) * (len(CASES) - 1)  # every loader x every case but missing
    assert max(p.stat().st_size for p in files) < 4096
