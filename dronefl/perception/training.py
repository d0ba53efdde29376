"""Train the YOLO11n target detector on rendered frames and ship it as ONNX (SPEC §3).

No pretrained weights can be downloaded, so the network starts from ``yolo11n.yaml`` (random
initialisation) and is trained with Ultralytics on the dataset of
:mod:`dronefl.perception.dataset`. Colour is what tells the targets apart, so the hue
augmentation is off; everything else is Ultralytics' default recipe (mosaic, scale, flips).
The best checkpoint (by validation mAP50-95) is exported to ONNX (fixed input
``imgsz x imgsz``, no NMS inside: :class:`~dronefl.perception.yolo.YoloDetector` decodes it).

All Ultralytics state (settings, runs) stays in the run folder; ``YOLO_OFFLINE=1``.
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from dronefl.perception.dataset import DatasetManifest
from dronefl.perception.nms_compat import ensure_torchvision_nms
from dronefl.perception.palette import COLOUR_NAMES
from dronefl.perception.quality import EnvironmentMetrics
from dronefl.serialize import load_result, save_result

#: Shipped detector weights and their sidecar inside the package.
DETECTOR_ASSET = "detector.onnx"
DETECTOR_SIDECAR = "detector.json"


@dataclass(frozen=True)
class TrainConfig:
    """Training recipe. ``imgsz`` px is the network input (frames are resized from 640 px)."""

    imgsz: int = 320
    epochs: int = 22
    batch: int = 16
    workers: int = 1
    threads: int = 2
    close_mosaic: int = 5
    patience: int = 100
    seed: int = 0

    def __post_init__(self) -> None:
        if self.imgsz % 32:
            raise ValueError(
                f"imgsz must be a multiple of 32 (the network stride), got {self.imgsz}"
            )
        if min(self.epochs, self.batch, self.threads) < 1 or self.workers < 0:
            raise ValueError("epochs, batch and threads must be >= 1 and workers >= 0")


@dataclass(frozen=True)
class TrainingRecord:
    """One training run (``train.json``): its ``config``, the ``data`` YAML, the wall time
    ``train_seconds`` (s) on ``torch_threads`` threads, the ``best_checkpoint`` (by validation
    mAP50-95) and the ``onnx`` file exported from it."""

    config: TrainConfig
    data: Path
    train_seconds: float
    torch_threads: int
    best_checkpoint: Path
    onnx: Path


@dataclass(frozen=True)
class DetectorSidecar:
    """The JSON shipped beside the ONNX weights (``detector.json``).

    ``classes``: network class -> target name; ``imgsz``: the input side (px) and ``input`` its
    layout; ``command``: what made the weights; ``dataset``: the manifest of the training data;
    ``training``: the run's record; ``metrics``: per environment, filled in by
    ``dronefl detector evaluate`` (None until then).
    """

    classes: dict[int, str]
    imgsz: int
    input: str
    command: str
    dataset: DatasetManifest
    training: TrainingRecord
    metrics: dict[str, EnvironmentMetrics] | None = None

    def save(self, path: Path) -> Path:
        """Write the sidecar to ``path``."""
        return save_result(path, self)

    @classmethod
    def load(cls, path: Path) -> DetectorSidecar:
        """Read a sidecar; :class:`~dronefl.serialize.ResultError` names a bad file."""
        return load_result(cls, path)


def prepare_ultralytics(run_dir: Path) -> None:
    """Point Ultralytics' settings into ``run_dir``, forbid downloads, fix ``torchvision::nms``.

    Must run before ``ultralytics`` is first imported (it reads the settings at import).
    """
    os.environ.setdefault("YOLO_CONFIG_DIR", str(run_dir / "ultralytics-config"))
    os.environ["YOLO_OFFLINE"] = "1"
    ensure_torchvision_nms()


def train_detector(data_yaml: Path, run_dir: Path, config: TrainConfig) -> TrainingRecord:
    """Train on ``data_yaml``, export ONNX; returns the training record (also written to
    ``run_dir/train.json``) with the paths of the best checkpoint and the ONNX file."""
    if not data_yaml.is_file():
        raise FileNotFoundError(f"no dataset file {data_yaml}: run `dronefl detector dataset`")
    run_dir.mkdir(parents=True, exist_ok=True)
    prepare_ultralytics(run_dir)
    import torch
    from ultralytics import YOLO

    torch.set_num_threads(config.threads)
    model = YOLO("yolo11n.yaml")
    start = time.perf_counter()
    model.train(
        data=str(data_yaml.resolve()), imgsz=config.imgsz, epochs=config.epochs,
        batch=config.batch, workers=config.workers, device="cpu", seed=config.seed,
        deterministic=True, patience=config.patience, close_mosaic=config.close_mosaic,
        project=str(run_dir.resolve()), name="train", exist_ok=True, pretrained=False,
        amp=False, plots=False, hsv_h=0.0, cache="ram", verbose=False,
    )  # fmt: skip
    train_s = time.perf_counter() - start
    best = run_dir / "train" / "weights" / "best.pt"
    onnx_path = Path(
        YOLO(str(best)).export(format="onnx", imgsz=config.imgsz, simplify=False, dynamic=False)
    )
    record = TrainingRecord(config, data_yaml.resolve(), train_s, config.threads, best, onnx_path)
    save_result(run_dir / "train.json", record)
    return record


def detector_sidecar(dataset: Path, record: TrainingRecord, command: str) -> DetectorSidecar:
    """The sidecar shipped beside the ONNX weights: classes, input size, the command that made
    them, the dataset's size and recipe, training time. ``metrics`` is filled in by
    ``dronefl detector evaluate``."""
    if not (dataset / "dataset.json").is_file():
        raise FileNotFoundError(f"no dataset.json in {dataset}")
    return DetectorSidecar(
        classes={i: f"target {i + 1} ({name})" for i, name in enumerate(COLOUR_NAMES)},
        imgsz=record.config.imgsz,
        input="RGB float32 (1, 3, imgsz, imgsz) in [0, 1], letterboxed from the 640 px frame",
        command=command,
        dataset=DatasetManifest.load(dataset),
        training=record,
    )


def ship_detector(onnx_path: Path, sidecar: DetectorSidecar, assets: Path | None = None) -> Path:
    """Copy ``onnx_path`` into the package assets with its JSON ``sidecar``; returns the path."""
    folder = assets or Path(str(resources.files("dronefl") / "assets"))
    folder.mkdir(parents=True, exist_ok=True)
    target = folder / DETECTOR_ASSET
    shutil.copyfile(onnx_path, target)
    sidecar.save(folder / DETECTOR_SIDECAR)
    return target
