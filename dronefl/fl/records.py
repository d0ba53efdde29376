"""The one place where Flower's string-keyed records meet DroneFL's typed objects.

Everything that crosses the cloud-drone link or the run configuration is converted here:

* :class:`FlSettings` <-> the run config (``UserConfig``: flat str -> scalar),
* model state dicts <-> ``ArrayRecord``,
* :class:`TrainInstructions` <- the ``ConfigRecord`` a strategy sends,
* :class:`ClientReport` <-> the ``MetricRecord`` a drone sends back.
"""

from __future__ import annotations

import math
from dataclasses import MISSING, asdict, dataclass, fields
from pathlib import Path

import torch
from flwr.app import ArrayRecord, ConfigRecord, MetricRecord

from dronefl.fl.methods import METHODS, Method
from dronefl.models.model import PredictorConfig
from dronefl.models.train import TrainConfig
from dronefl.models.windows import WindowSpec

#: Record keys (Flower's strategies use "arrays", "config", "num-examples", "proximal-mu").
ARRAYS_KEY = "arrays"
METRICS_KEY = "metrics"
NUM_EXAMPLES_KEY = "num-examples"
ROUND_KEY = "server-round"
PROXIMAL_MU_KEY = "proximal-mu"
PARTITION_KEY = "partition-id"
DRONE_KEY = "drone-id"
LABEL_SOURCES = ("ground_truth", "tracks")


class SettingsError(ValueError):
    """A run configuration value is missing, of the wrong type or out of range."""


@dataclass(frozen=True)
class FlSettings:
    """Everything a federated run needs, shared by the ServerApp and every ClientApp.

    ``run_dir``: recorded run folder (``drone_<id>.npz`` + ``ground_truth.npz``);
    ``out_dir``: where the server writes ``history.json`` and ``checkpoint.npz``;
    ``method``: a key of :data:`dronefl.fl.methods.METHODS`; ``rounds`` global rounds;
    ``past_steps``/``future_steps``/``stride`` (samples) the windows; ``epochs``, ``lr``,
    ``batch_size`` local training; ``proximal_mu`` FedProx's mu (used by ``fedprox`` only);
    ``seed`` model initialisation and training seeds; ``resume`` continue from the checkpoint;
    ``labels`` ``ground_truth`` (``ground_truth.npz``) or ``tracks`` (the cloud's fused tracks in
    ``tracks.npz``: pseudo-labels, as in the closed loop).
    """

    run_dir: str
    out_dir: str
    method: str = "dronefl"
    rounds: int = 50
    past_steps: int = 10
    future_steps: int = 5
    stride: int = 5
    epochs: int = 10
    lr: float = 1e-3
    batch_size: int = 128
    proximal_mu: float = 0.01
    seed: int = 0
    resume: bool = False
    labels: str = "ground_truth"

    def __post_init__(self) -> None:
        if self.labels not in LABEL_SOURCES:
            raise SettingsError(f"labels: {self.labels!r} is not one of {LABEL_SOURCES}")
        if self.method not in METHODS:
            raise SettingsError(f"method: unknown {self.method!r}; choose one of {list(METHODS)}")
        for name in ("rounds", "past_steps", "future_steps", "stride", "epochs", "batch_size"):
            if getattr(self, name) < 1:
                raise SettingsError(f"{name}: must be >= 1, got {getattr(self, name)}")
        if not self.lr > 0 or self.proximal_mu < 0:
            raise SettingsError("lr must be > 0 and proximal_mu >= 0")

    @property
    def method_spec(self) -> Method:
        return METHODS[self.method]

    @property
    def model(self) -> PredictorConfig:
        return self.method_spec.predictor(self.past_steps, self.future_steps)

    @property
    def windows(self) -> WindowSpec:
        return WindowSpec(
            self.past_steps, self.future_steps, relative=self.model.relative, stride=self.stride
        )

    def train_config(self, server_round: int, drone_id: int) -> TrainConfig:
        """Local training of ``drone_id`` in ``server_round``, seeded by both."""
        return TrainConfig(
            self.epochs, self.lr, self.batch_size, self.seed_for(server_round, drone_id)
        )

    def seed_for(self, server_round: int, drone_id: int) -> int:
        return self.seed * 1_000_003 + server_round * 1_009 + drone_id

    @property
    def checkpoint_path(self) -> Path:
        return Path(self.out_dir) / "checkpoint.npz"

    @property
    def history_path(self) -> Path:
        return Path(self.out_dir) / "history.json"

    def to_run_config(self) -> dict[str, str | int | float | bool]:
        """As a Flower run config (kebab-case keys, as in ``pyproject.toml``)."""
        return {k.replace("_", "-"): v for k, v in asdict(self).items()}

    @classmethod
    def from_run_config(cls, config: dict) -> FlSettings:
        """Parse a run config; raises :class:`SettingsError` naming the key."""
        values = {}
        for f in fields(cls):
            key = f.name.replace("_", "-")
            if key not in config:
                if f.default is MISSING:
                    raise SettingsError(f"run config: missing key {key!r}")
                continue
            kind = {"int": int, "float": float, "str": str, "bool": bool}[str(f.type)]
            value = config[key]
            if kind is float and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
                raise SettingsError(f"run config: {key!r} must be {f.type}, got {value!r}")
            values[f.name] = value
        return cls(**values)


def to_arrays(state: dict[str, torch.Tensor]) -> ArrayRecord:
    """A model state dict (or part of one) as an ``ArrayRecord``."""
    return ArrayRecord({k: v.detach().cpu().contiguous() for k, v in state.items()})


def to_state(arrays: ArrayRecord) -> dict[str, torch.Tensor]:
    """An ``ArrayRecord`` as a state dict of torch tensors."""
    return arrays.to_torch_state_dict()


@dataclass(frozen=True)
class TrainInstructions:
    """What the cloud asks of a drone for one round: the global ``server_round`` and FedProx's
    ``proximal_mu`` (0 for every other strategy)."""

    server_round: int
    proximal_mu: float = 0.0

    @classmethod
    def from_config(cls, config: ConfigRecord) -> TrainInstructions:
        if ROUND_KEY not in config:
            raise SettingsError(f"train config: missing {ROUND_KEY!r}")
        return cls(int(config[ROUND_KEY]), float(config.get(PROXIMAL_MU_KEY, 0.0)))


@dataclass(frozen=True)
class ClientReport:
    """A drone's reply: ``num_examples`` windows used, and ``value``: the training loss (m^2,
    last epoch) after training or the test MSE (m^2) after evaluation."""

    drone_id: int
    num_examples: int
    value: float

    def to_metrics(self) -> MetricRecord:
        return MetricRecord(
            {DRONE_KEY: self.drone_id, NUM_EXAMPLES_KEY: self.num_examples, "value": self.value}
        )

    @classmethod
    def from_metrics(cls, metrics: MetricRecord) -> ClientReport:
        for key in (DRONE_KEY, NUM_EXAMPLES_KEY, "value"):
            if key not in metrics:
                raise SettingsError(f"client metrics: missing {key!r}")
        value = float(metrics["value"])
        return cls(int(metrics[DRONE_KEY]), int(metrics[NUM_EXAMPLES_KEY]), value)

    @property
    def finite(self) -> bool:
        return math.isfinite(self.value)
