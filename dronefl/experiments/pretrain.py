"""Pretraining for the closed loop: models learned offline in the crop field (SPEC §8).

For a scenario, :func:`pretrain` records ``duration`` s of the crop field under the scripted
pilot (seed :data:`PRETRAIN_SEED`, never used by an evaluation episode) and trains, with
ground-truth labels and windows L_p -> L_f = 1:

* ``dronefl``: the position-invariant AdaIN model by federated learning (FedAvg on Flower);
  the fixed-distributed and DroneFL episodes both start from it;
* ``centralized``: the large model on the pooled windows of every drone, in the cloud;
* ``image``: the paper's centralized baseline, the image model
  (:class:`~dronefl.models.image.FrameTransformer`) on every drone's frames rendered through
  the JPEG uplink (:func:`~dronefl.perception.recorded_frames.render_run`, cached beside the
  recording), trained on the first 80 % of the steps (the setting of ``dronefl
  image-baseline``) and scored on the rest (:mod:`dronefl.experiments.pretrain_image`).

Results are cached under ``<folder>/<scenario name>/`` and keyed by content: the recording by a
hash of the scenario, the recording seed and duration and of the source code that records it
(:data:`RECORDING_CODE`; ``data-<hash>/``), each model by a hash of that, of every training
setting and of the code that trains (:data:`TRAINING_CODE`; ``<kind>-<hash>/checkpoint.npz``;
the image model: :data:`IMAGE_TRAINING_CODE`, ``image-<hash>/image_model.npz``), so an edited
scenario, a changed setting or changed code never reuses stale weights.
Pretraining runs its own Flower simulation and must be done before an episode starts its
session (:func:`pretrained_state`).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import torch

from dronefl.config import Scenario
from dronefl.experiments.fl_offline import run_centralized
from dronefl.experiments.pretrain_image import (
    IMAGE_PRETRAINING,
    IMAGE_TRAIN_FRACTION,
    load_image_state,
    pretrain_image,
)
from dronefl.experiments.simulate import simulate
from dronefl.fl.checkpoint import load_checkpoint, load_history
from dronefl.fl.records import FlSettings, fl_settings
from dronefl.fl.simulation import run_federated
from dronefl.models.image import ImageModelConfig
from dronefl.models.model import PredictorConfig
from dronefl.progress import progress_bar
from dronefl.settings import Setting

_PACKAGE = Path(__file__).resolve().parents[1]
PRETRAIN_SEED = 1000
KINDS = ("dronefl", "centralized", "image")
#: The package's files (paths relative to ``dronefl/``; a folder means its ``*.py``) that make
#: the crop-field recording and those that train on it: a change to any of them changes the
#: cache key (a refactor too: it re-pretrains once, 3-4 min, rather than risk stale weights).
RECORDING_CODE = ("sim", "perception", "config.py", "logs.py", "experiments/simulate.py",
                  "assets/projection_noise.json")  # fmt: skip
TRAINING_CODE = ("models", "fl", "experiments/fl_offline.py", "experiments/pretrain.py")
#: The files that train the image model (its frames are part of the recording's key).
IMAGE_TRAINING_CODE = ("models/image.py", "logs.py", "experiments/pretrain_image.py")


@dataclass(frozen=True)
class PretrainSpec:
    """What is pretrained: ``kind`` (one of :data:`KINDS`) for ``scenario`` as ``setting``
    says (its model, training and pretraining sub-configs: ``pretraining.seconds`` of crop
    field recorded with seed ``recording_seed``, windows L_p -> 1 every ``pretraining.stride``
    samples, ``pretraining.rounds`` FL rounds, or rounds x E epochs of centralized training),
    with a run of detections hidden in a ``detection_gaps`` fraction of the training windows
    (:func:`~dronefl.models.train.cut_detection_gaps`; the setting's probability resolved,
    ``auto`` chosen by :func:`~dronefl.experiments.gap_choice.resolve_gaps`)."""

    scenario: Scenario
    setting: Setting
    kind: str = "dronefl"
    detection_gaps: float = 0.0
    recording_seed: int = PRETRAIN_SEED

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"pretrained model kind must be one of {KINDS}, got {self.kind!r}")
        if not 0.0 <= self.detection_gaps <= 1.0:
            raise ValueError(f"detection_gaps: must be in [0, 1], got {self.detection_gaps}")

    @property
    def duration(self) -> float:
        """Seconds of crop field recorded."""
        return self.setting.pretraining.seconds

    @property
    def past_steps(self) -> int:
        """L_p of the pretrained model."""
        return self.setting.model.past_steps

    @property
    def stride(self) -> int:
        """Samples between training windows."""
        return self.setting.pretraining.stride

    @property
    def rounds(self) -> int:
        """FL rounds (or rounds x E epochs of centralized training)."""
        return self.setting.pretraining.rounds

    @property
    def data_key(self) -> str:
        """Hash of what the recording depends on."""
        return _digest(
            [self.scenario.content_hash, self.duration, self.recording_seed,
             package_digest(RECORDING_CODE)]
        )  # fmt: skip

    def settings(self, folder: Path) -> FlSettings:
        """The Flower/centralized training settings, writing under ``folder`` (the ``image``
        kind has none: its training is :data:`IMAGE_PRETRAINING`, its folder :meth:`image_dir`)."""
        if self.kind == "image":
            raise ValueError("the image model is not trained by Flower: see image_dir")
        root = Path(folder) / self.scenario.name
        field = self.scenario.field
        base = fl_settings(
            self.setting, self.kind, run_dir=str(self.data_dir(folder)), out_dir="",
            rounds=self.rounds, future_steps=1, stride=self.stride, seed=0,
            field_m=(field.width, field.height), detection_gaps=self.detection_gaps,
        )  # fmt: skip
        key = _digest(
            [self.data_key, base.training_key(), repr(base.model), package_digest(TRAINING_CODE)]
        )
        return dataclasses.replace(base, out_dir=str(root / f"{self.kind}-{key}"))

    @property
    def model(self) -> PredictorConfig:
        """The architecture pretrained (and flown by the episodes that start from it); the
        ``image`` kind's is :meth:`image_model`."""
        if self.kind == "image":
            raise ValueError("the image model is not a trajectory predictor: see image_model")
        return self.settings(Path(".")).model

    @property
    def image_model(self) -> ImageModelConfig:
        """The image model's architecture: a slot per target of the scenario, L_p frames."""
        return ImageModelConfig(len(self.scenario.target_ids), self.past_steps)

    def data_dir(self, folder: Path) -> Path:
        """Where the crop-field recording (and its rendered frames) is cached."""
        return Path(folder) / self.scenario.name / f"data-{self.data_key}"

    def image_dir(self, folder: Path) -> Path:
        """Where the ``image`` kind's weights and ``pretrain.json`` are cached."""
        key = _digest(
            [self.data_key, self.stride, IMAGE_TRAIN_FRACTION,
             dataclasses.asdict(self.image_model), dataclasses.asdict(IMAGE_PRETRAINING),
             package_digest(IMAGE_TRAINING_CODE)]
        )  # fmt: skip
        return Path(folder) / self.scenario.name / f"image-{key}"

    def model_path(self, folder: Path) -> Path:
        """The file that holds the pretrained weights."""
        if self.kind == "image":
            return self.image_dir(folder) / "image_model.npz"
        return self.settings(folder).checkpoint_path


def pretrain(
    spec: PretrainSpec, folder: Path, progress: bool = True, done: int = 0
) -> dict[str, torch.Tensor]:
    """Record the crop field (if not yet recorded) and train ``spec.kind``, going on from the
    checkpoint of a pretraining stopped early; returns its weights. ``done``: the rounds that
    checkpoint holds (where the progress bar starts). Runs a Flower simulation for
    ``dronefl``: never call it inside another one."""
    data = spec.data_dir(folder)
    if not (data / "ground_truth.npz").is_file():
        simulate(
            spec.scenario,
            environment="crop_field",
            duration=spec.duration,
            seed=spec.recording_seed,
            out=data,
            progress=progress,
            plot=False,
        )
    if spec.kind == "image":
        return pretrain_image(
            data, spec.model_path(folder), spec.image_model, spec.stride,
            f"pretrain {spec.scenario.name} image", progress,
        )  # fmt: skip
    # A pretraining stopped early (Ctrl-C, a kill) goes on from its last checkpoint: the
    # folder's key names the setting and the training code, so a checkpoint there is this run's.
    settings = dataclasses.replace(spec.settings(folder), resume=True)
    name = f"pretrain {spec.scenario.name} {spec.kind}"
    with progress_bar(name, spec.rounds, progress, completed=done) as advance:
        train = run_federated if spec.kind == "dronefl" else run_centralized
        train(settings, on_round=lambda _: advance(1))
    return load_checkpoint(settings.checkpoint_path, settings.history_path, spec.kind).state


def pretrained_state(
    spec: PretrainSpec, folder: Path, progress: bool = True
) -> dict[str, torch.Tensor]:
    """The cached pretrained weights of ``spec``, pretraining them if missing."""
    if spec.kind == "image":  # cached weights need no recording
        path = spec.model_path(folder)
        return load_image_state(path) if path.is_file() else pretrain(spec, folder, progress)
    settings = spec.settings(folder)
    done = 0
    if settings.checkpoint_path.is_file():
        checkpoint = load_checkpoint(settings.checkpoint_path, settings.history_path, spec.kind)
        if checkpoint.server_round >= settings.rounds:
            return checkpoint.state
        done = checkpoint.server_round
    return pretrain(spec, folder, progress=progress, done=done)


def held_out_mse(spec: PretrainSpec, folder: Path) -> dict[int, float]:
    """The pretrained model's prediction error per drone (MSE, m^2, one step ahead) on the
    held-out part of the crop-field recording: the chronologically last 1 - train_fraction
    (20 %) of each drone's windows, which pretraining never trains on. Read from the last
    round of the run's history (:class:`~dronefl.fl.checkpoint.CheckpointError` when it is
    missing or short of ``rounds``; ``ValueError`` when no drone evaluated in that round).
    The ``image`` kind's is the masked MSE of its held-out windows, from ``pretrain.json``."""
    if spec.kind == "image":
        report = json.loads((spec.image_dir(folder) / "pretrain.json").read_text())
        return {int(d): float(v) for d, v in sorted(report["held_out_mse"].items())}
    settings = spec.settings(folder)
    history = load_history(settings.history_path, settings.rounds)
    if not history or not history[-1].test_mse:
        raise ValueError(f"{settings.history_path}: no evaluated round")
    return dict(sorted(history[-1].test_mse.items()))


@functools.cache
def package_digest(parts: tuple[str, ...]) -> str:
    """:func:`code_digest` of this package's ``parts``, read once per process: the code a
    process runs is the code it imported, whatever is edited on disk since."""
    return code_digest(parts, _PACKAGE)


def code_digest(parts: tuple[str, ...], root: Path) -> str:
    """SHA-256 (12 hex digits) of the files ``parts`` under ``root`` (a folder: its ``*.py``,
    recursively), by path relative to ``root`` and content; a missing part is an error."""
    digest = hashlib.sha256()
    for part in parts:
        path = root / part
        if not path.exists():
            raise FileNotFoundError(f"{path}: listed in the pretraining cache key, missing")
        for file in sorted(path.rglob("*.py")) if path.is_dir() else [path]:
            digest.update(file.relative_to(root).as_posix().encode() + b"\0")
            digest.update(file.read_bytes() + b"\0")
    return digest.hexdigest()[:12]


def _digest(parts: list) -> str:
    text = json.dumps(parts, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:12]
