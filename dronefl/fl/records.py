"""The one place where Flower's string-keyed records meet DroneFL's typed objects.

Everything that crosses the cloud-drone link or the run configuration is converted here:

* :class:`FlSettings` <-> the run config (``UserConfig``: flat str -> scalar),
* model state dicts <-> ``ArrayRecord``: named (:func:`to_arrays`, for local storage) or, on
  the wire, one flat vector in fp32 or fp16 (:class:`WeightLayout`),
* :class:`TrainInstructions` <- the ``ConfigRecord`` a strategy sends,
* :class:`ClientReport` <-> the ``MetricRecord`` a drone sends back,
* :class:`RoundRecord` <-> one entry of ``history.json`` (the round history).
"""

from __future__ import annotations

import math
from dataclasses import MISSING, asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import torch
from flwr.app import Array, ArrayRecord, ConfigRecord, Message, MetricRecord, RecordDict

from dronefl.fl.fault_list import parse_faults
from dronefl.fl.methods import METHODS, Method
from dronefl.models.model import ADAIN_SITES, PredictorConfig, TrajectoryTransformer, build_model
from dronefl.models.train import OPTIMIZERS, TrainConfig
from dronefl.models.windows import PAPER_FIELD_M, WindowSpec
from dronefl.settings import AGGREGATIONS, DRIFT_CORRECTIONS, WEIGHT_DTYPES, Setting

#: Record keys (Flower's strategies use "arrays", "config", "num-examples", "proximal-mu").
ARRAYS_KEY = "arrays"
CONFIG_KEY = "config"
METRICS_KEY = "metrics"
VALUE_KEY = "value"
MEAN_TEST_MSE_KEY = "mean-test-mse"
NUM_EXAMPLES_KEY = "num-examples"
ROUND_KEY = "server-round"
PROXIMAL_MU_KEY = "proximal-mu"
PARTITION_KEY = "partition-id"
DRONE_KEY = "drone-id"
RUN_DIR_KEY = "run-dir"
WEIGHTS_KEY = "weights"
#: SCAFFOLD's control variate, beside the weights on the wire (same layout).
CONTROL_KEY = "control"
#: Where a FedPer drone keeps its personal output head (``context.state``).
PERSONAL_KEY = "personal-head"
LABEL_SOURCES = ("ground_truth", "tracks")
#: The factor on the lr in the last rounds of a stepped schedule (``lr_step_at`` < 1).
LR_STEP_FACTOR = 0.1


#: The :class:`FlSettings` fields that say where a run reads and writes, not what it trains.
WHERE_FIELDS: tuple[str, ...] = ("run_dir", "out_dir", "resume")


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
    ``tracks_<id>.npz`` or ``tracks.npz``: pseudo-labels, as in the closed loop; see
    :func:`~dronefl.models.windows.load_drone_split`); ``weights_dtype`` the number format
    of the weights on the wire (``float16`` halves the bytes; training stays in fp32);
    ``train_fraction`` the chronologically first part of each drone's windows it trains on, the
    rest being its test set (1.0: train on everything and skip federated evaluation, as in the
    closed loop, where evaluation is not part of the method); ``aggregation`` one of
    :data:`AGGREGATIONS`; ``round_timeout`` s the cloud waits for the drones' replies in each
    exchange after the first (a drone that has not answered by then is left out of the round;
    the first exchange waits for the drones to start up, see ``server_app.StartupGrid``);
    ``faults`` injected drone faults, for tests (see :mod:`dronefl.fl.faults`; empty: none);
    ``field_width`` x
    ``field_height`` m the scenario's field (the frame of absolute positions);
    ``adain_sites`` (comma-separated, see :data:`dronefl.models.model.ADAIN_SITES`) and
    ``head_style_init`` where the models with AdaIN condition on the altitude and how the
    head's style starts; ``box_size`` how DroneFL's models read box sizes (see
    :data:`dronefl.models.model.BOX_SIZES`; the FL baselines always read ``image``);
    ``optimizer`` the local (and pooled) optimiser, ``adam`` or ``sgd`` with momentum (see
    :class:`~dronefl.models.train.TrainConfig`); ``drift_correction`` one of
    :data:`DRIFT_CORRECTIONS` (``scaffold``: every drone keeps a control variate c_i, the cloud
    averages them into c, sent beside the weights, and the local steps follow
    ``g_i - c_i + c``; needs ``optimizer = "sgd"``); ``lr_step_at`` the fraction of the
    rounds trained at ``lr``, the rest at ``lr`` x :data:`LR_STEP_FACTOR` (1.0: a constant
    lr; see :meth:`lr_of`); ``detection_gaps`` the probability that a training window has a
    run of its detections hidden (:func:`~dronefl.models.train.cut_detection_gaps`; 0: none,
    the closed loop's online rounds, whose orchard windows have real gaps). A setting's
    model and training become these in :func:`fl_settings`.
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
    weights_dtype: str = "float32"
    train_fraction: float = 0.8
    aggregation: str = "mean"
    round_timeout: float = 3600.0
    faults: str = ""
    field_width: float = PAPER_FIELD_M[0]
    field_height: float = PAPER_FIELD_M[1]
    adain_sites: str = ",".join(ADAIN_SITES)
    head_style_init: str = "altitude"
    box_size: str = "image"
    optimizer: str = "adam"
    drift_correction: str = "none"
    lr_step_at: float = 1.0
    detection_gaps: float = 0.0

    def __post_init__(self) -> None:
        if self.optimizer not in OPTIMIZERS:
            raise SettingsError(
                f"optimizer: {self.optimizer!r} is not one of {', '.join(OPTIMIZERS)}"
            )
        if self.drift_correction not in DRIFT_CORRECTIONS:
            raise SettingsError(
                f"drift-correction: {self.drift_correction!r} is not one of "
                f"{', '.join(DRIFT_CORRECTIONS)}"
            )
        if self.scaffold and self.optimizer != "sgd":
            raise SettingsError(
                "drift-correction: 'scaffold' needs optimizer 'sgd' (its control variate "
                f"assumes SGD steps), got {self.optimizer!r}"
            )
        if self.scaffold and self.method_spec.proximal:
            raise SettingsError("drift-correction: 'scaffold' and FedProx are alternatives")
        if self.labels not in LABEL_SOURCES:
            raise SettingsError(f"labels: {self.labels!r} is not one of {LABEL_SOURCES}")
        if self.weights_dtype not in WEIGHT_DTYPES:
            raise SettingsError(
                f"weights-dtype: {self.weights_dtype!r} is not one of {', '.join(WEIGHT_DTYPES)}"
            )
        if self.method not in METHODS:
            raise SettingsError(f"method: unknown {self.method!r}; choose one of {list(METHODS)}")
        for name in ("rounds", "past_steps", "future_steps", "stride", "epochs", "batch_size"):
            if getattr(self, name) < 1:
                raise SettingsError(f"{name}: must be >= 1, got {getattr(self, name)}")
        if not 0.0 < self.train_fraction <= 1.0:
            raise SettingsError(f"train-fraction: must be in (0, 1], got {self.train_fraction}")
        if not self.lr > 0 or self.proximal_mu < 0:
            raise SettingsError("lr must be > 0 and proximal_mu >= 0")
        if not 0.0 < self.lr_step_at <= 1.0:
            raise SettingsError(f"lr-step-at: must be in (0, 1], got {self.lr_step_at}")
        if not 0.0 <= self.detection_gaps <= 1.0:
            raise SettingsError(f"detection-gaps: must be in [0, 1], got {self.detection_gaps}")
        if self.aggregation not in AGGREGATIONS:
            raise SettingsError(
                f"aggregation: {self.aggregation!r} is not one of {', '.join(AGGREGATIONS)}"
            )
        if not self.round_timeout > 0:
            raise SettingsError(f"round-timeout: must be > 0 s, got {self.round_timeout}")
        if self.faults:
            try:
                parse_faults(self.faults)
            except ValueError as exc:
                raise SettingsError(str(exc)) from None
        if not (self.field_width > 0 and self.field_height > 0):
            raise SettingsError("field-width and field-height must be > 0 m")
        try:
            self.model  # noqa: B018 - builds and validates the predictor configuration
        except ValueError as exc:
            raise SettingsError(f"model: {exc}") from None

    @property
    def scaffold(self) -> bool:
        """Whether the rounds carry SCAFFOLD's control variates."""
        return self.drift_correction == "scaffold"

    @property
    def method_spec(self) -> Method:
        return METHODS[self.method]

    @property
    def model(self) -> PredictorConfig:
        """The architecture this run trains (the method's, in the run's field, with the
        run's AdaIN placement)."""
        return self.method_spec.predictor(
            self.past_steps,
            self.future_steps,
            field_m=(self.field_width, self.field_height),
            adain_sites=tuple(self.adain_sites.split(",")),
            head_style_init=self.head_style_init,
            box_size=self.box_size,
        )

    @property
    def layout(self) -> WeightLayout:
        """The wire layout of the global weights (FedPer's personal head never travels)."""
        return WeightLayout.of(
            global_part(build_model(self.model).state_dict(), self), self.weights_dtype
        )

    @property
    def windows(self) -> WindowSpec:
        return WindowSpec(
            self.past_steps,
            self.future_steps,
            relative=self.model.relative,
            stride=self.stride,
            train_fraction=self.train_fraction,
            field_m=(self.field_width, self.field_height),
        )

    @property
    def evaluates(self) -> bool:
        """Whether the drones hold test windows, and so whether rounds evaluate."""
        return self.train_fraction < 1.0

    def train_config(self, server_round: int, drone_id: int) -> TrainConfig:
        """Local training of ``drone_id`` in ``server_round``, seeded by both."""
        return TrainConfig(
            self.epochs,
            self.lr_of(server_round),
            self.batch_size,
            self.seed_for(server_round, drone_id),
            self.optimizer,
            self.detection_gaps,
        )

    def lr_of(self, server_round: int) -> float:
        """The local lr of ``server_round``: ``lr``, and ``lr`` x :data:`LR_STEP_FACTOR` in
        the rounds after the first round(``lr_step_at`` x ``rounds``) (1.0: every round at
        ``lr``, also past ``rounds``, as a closed loop's online rounds may go)."""
        if self.lr_step_at < 1.0 and server_round > round(self.lr_step_at * self.rounds):
            return self.lr * LR_STEP_FACTOR
        return self.lr

    def seed_for(self, server_round: int, drone_id: int) -> int:
        return self.seed * 1_000_003 + server_round * 1_009 + drone_id

    @property
    def checkpoint_path(self) -> Path:
        return Path(self.out_dir) / "checkpoint.npz"

    @property
    def history_path(self) -> Path:
        return Path(self.out_dir) / "history.json"

    def training_key(self) -> dict[str, str | int | float | bool]:
        """Every setting that decides what a run trains, i.e. all but where it reads and
        writes and whether it resumes (:data:`WHERE_FIELDS`): two runs with equal keys train
        the same weights."""
        return {k: v for k, v in asdict(self).items() if k not in WHERE_FIELDS}

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


def global_part(state: dict[str, torch.Tensor], settings: FlSettings) -> dict[str, torch.Tensor]:
    """The weights of ``state`` that are averaged: all but FedPer's personal output head."""
    if not settings.method_spec.personal:
        return state
    return {k: v for k, v in state.items() if not k.startswith(TrajectoryTransformer.HEAD)}


def to_arrays(state: dict[str, torch.Tensor]) -> ArrayRecord:
    """A model state dict (or part of one) as an ``ArrayRecord`` of named tensors (for a
    drone's own storage; the wire format is :class:`WeightLayout`)."""
    return ArrayRecord({k: v.detach().cpu().contiguous() for k, v in state.items()})


def to_state(arrays: ArrayRecord) -> dict[str, torch.Tensor]:
    """An ``ArrayRecord`` as a state dict of torch tensors."""
    return arrays.to_torch_state_dict()


@dataclass(frozen=True)
class WeightLayout:
    """How model weights travel between cloud and drones: one flat vector.

    Both ends build the same model, so names and shapes need not be sent: the weights go as
    ``ArrayRecord({"weights": w})`` with ``w`` the concatenation of the tensors in ``names``
    order, cast to ``dtype``. One array instead of one per tensor saves Flower's per-array
    framing (a ~170 B header and content hash per tensor: 24 kB for the 69 tensors of the
    DroneFL model, as much as half its fp32 weights). ``float16`` halves the payload; the
    receiver casts back to fp32 (relative rounding error <= 2^-11).
    """

    names: tuple[str, ...]
    shapes: tuple[tuple[int, ...], ...]
    dtype: str = "float32"

    def __post_init__(self) -> None:
        if self.dtype not in WEIGHT_DTYPES:
            raise SettingsError(f"weights-dtype: {self.dtype!r} is not one of {WEIGHT_DTYPES}")

    @classmethod
    def of(cls, state: dict[str, torch.Tensor], dtype: str = "float32") -> WeightLayout:
        """The layout of ``state`` (e.g. a freshly built model's state dict)."""
        return cls(tuple(state), tuple(tuple(v.shape) for v in state.values()), dtype)

    @property
    def size(self) -> int:
        """Number of weights."""
        return sum(math.prod(shape) for shape in self.shapes)

    def pack(
        self, state: dict[str, torch.Tensor], control: dict[str, torch.Tensor] | None = None
    ) -> ArrayRecord:
        """``state`` (same names and shapes) as one flat array of ``dtype``; with ``control``
        (SCAFFOLD's control variate, same layout) a second array beside it."""
        arrays = {WEIGHTS_KEY: self._flat(state)}
        if control is not None:
            arrays[CONTROL_KEY] = self._flat(control)
        return ArrayRecord(arrays)

    def _flat(self, state: dict[str, torch.Tensor]) -> Array:
        if set(state) != set(self.names):
            raise SettingsError("weights: the state does not hold the layout's tensors")
        flat = torch.cat([state[k].detach().cpu().reshape(-1).float() for k in self.names])
        return Array(flat.numpy().astype(self.dtype))

    def unpack(self, arrays: ArrayRecord) -> dict[str, torch.Tensor]:
        """The fp32 state dict in an ``ArrayRecord`` made by :meth:`pack`."""
        if set(arrays.keys()) - {CONTROL_KEY} != {WEIGHTS_KEY}:
            raise SettingsError(f"weights: expected one array {WEIGHTS_KEY!r}")
        return self._unflat(arrays, WEIGHTS_KEY)

    def unpack_control(self, arrays: ArrayRecord) -> dict[str, torch.Tensor]:
        """The control variate in an ``ArrayRecord`` made by :meth:`pack` with one."""
        if CONTROL_KEY not in arrays:
            raise SettingsError(f"weights: no {CONTROL_KEY!r} array (SCAFFOLD) in the message")
        return self._unflat(arrays, CONTROL_KEY)

    def zeros(self) -> dict[str, torch.Tensor]:
        """A state of zeros in this layout (SCAFFOLD's first control variates)."""
        return {k: torch.zeros(shape) for k, shape in zip(self.names, self.shapes, strict=True)}

    def _unflat(self, arrays: ArrayRecord, key: str) -> dict[str, torch.Tensor]:
        flat = arrays[key].numpy()
        if flat.shape != (self.size,):
            raise SettingsError(f"weights: expected {self.size} values, got shape {flat.shape}")
        values = torch.from_numpy(flat.astype(np.float32))
        parts = torch.split(values, [math.prod(shape) for shape in self.shapes])
        return {
            name: part.reshape(shape).clone()
            for name, part, shape in zip(self.names, parts, self.shapes, strict=True)
        }


@dataclass(frozen=True)
class TrainInstructions:
    """What the cloud asks of a drone for one round: the global ``server_round``, FedProx's
    ``proximal_mu`` (0 for every other strategy) and, in the closed loop, the ``run_dir``
    holding the data recorded so far (else the run config's)."""

    server_round: int
    proximal_mu: float = 0.0
    run_dir: str | None = None

    @classmethod
    def from_config(cls, config: ConfigRecord) -> TrainInstructions:
        if ROUND_KEY not in config:
            raise SettingsError(f"train config: missing {ROUND_KEY!r}")
        run_dir = str(config[RUN_DIR_KEY]) if RUN_DIR_KEY in config else None
        return cls(int(config[ROUND_KEY]), float(config.get(PROXIMAL_MU_KEY, 0.0)), run_dir)


@dataclass(frozen=True)
class ClientReport:
    """A drone's reply: ``num_examples`` windows used, and ``value``: the training loss (m^2,
    last epoch) after training or the test MSE (m^2) after evaluation."""

    drone_id: int
    num_examples: int
    value: float

    def to_metrics(self) -> MetricRecord:
        return MetricRecord(
            {DRONE_KEY: self.drone_id, NUM_EXAMPLES_KEY: self.num_examples, VALUE_KEY: self.value}
        )

    @classmethod
    def from_metrics(cls, metrics: MetricRecord) -> ClientReport:
        for key in (DRONE_KEY, NUM_EXAMPLES_KEY, VALUE_KEY):
            if key not in metrics:
                raise SettingsError(f"client metrics: missing {key!r}")
        value = float(metrics[VALUE_KEY])
        return cls(int(metrics[DRONE_KEY]), int(metrics[NUM_EXAMPLES_KEY]), value)

    @property
    def finite(self) -> bool:
        return math.isfinite(self.value)


def reply_report(content: RecordDict) -> ClientReport:
    """The :class:`ClientReport` in a drone's reply (its one ``MetricRecord``)."""
    if len(content.metric_records) != 1:
        raise SettingsError("reply must hold one MetricRecord")
    return ClientReport.from_metrics(next(iter(content.metric_records.values())))


def reply_drone_id(message: Message) -> int | None:
    """The drone id a reply names in its metrics, or None (a failed or empty reply)."""
    if not message.has_content():
        return None
    for metrics in message.content.metric_records.values():
        if DRONE_KEY in metrics:
            return int(metrics[DRONE_KEY])
    return None


def round_of(message: Message) -> int:
    """The global round a strategy wrote into a message's config (0 if none)."""
    for config in message.content.config_records.values():
        if ROUND_KEY in config:
            return int(config[ROUND_KEY])
    return 0


def mean_test_mse_metrics(value: float) -> MetricRecord:
    """What ``aggregate_evaluate`` returns to Flower: the round's mean test MSE (m^2)."""
    return MetricRecord({MEAN_TEST_MSE_KEY: value})


@dataclass(frozen=True)
class RoundRecord:
    """One finished global round, as the server (or the cloud, for pooled training) saw it.

    ``test_mse``: drone id -> MSE (m^2) of the global model on that drone's test windows
    (empty when rounds do not evaluate); ``train_loss``: drone id -> last-epoch training loss
    (m^2; key 0 is the cloud for pooled training); ``rejected``: updates left out, with why;
    ``bytes_down`` / ``bytes_up``: message type (``train``, ``evaluate``) -> bytes sent to /
    received from all drones this round.
    """

    server_round: int
    test_mse: dict[int, float] = field(default_factory=dict)
    train_loss: dict[int, float] = field(default_factory=dict)
    rejected: tuple[str, ...] = ()
    bytes_down: dict[str, int] = field(default_factory=dict)
    bytes_up: dict[str, int] = field(default_factory=dict)

    @property
    def mean_test_mse(self) -> float | None:
        """Unweighted mean over drones of the test MSE, m^2 (the paper's "average test MSE
        across drones"); None when no drone evaluated."""
        if not self.test_mse:
            return None
        return float(np.mean(list(self.test_mse.values())))

    def to_json(self) -> dict:
        """The ``history.json`` entry (string keys for drone ids, as JSON needs)."""
        return {
            "round": self.server_round,
            "mean_test_mse": self.mean_test_mse,
            "test_mse": {str(k): v for k, v in sorted(self.test_mse.items())},
            "train_loss": {str(k): v for k, v in sorted(self.train_loss.items())},
            "rejected": list(self.rejected),
            "bytes": {"down": dict(self.bytes_down), "up": dict(self.bytes_up)},
        }

    @classmethod
    def from_json(cls, entry: dict) -> RoundRecord:
        """Parse a ``history.json`` entry; raises :class:`SettingsError` naming the field."""
        try:
            return cls(
                server_round=int(entry["round"]),
                test_mse={int(k): float(v) for k, v in entry["test_mse"].items()},
                train_loss={int(k): float(v) for k, v in entry["train_loss"].items()},
                rejected=tuple(str(r) for r in entry["rejected"]),
                bytes_down={str(k): int(v) for k, v in entry["bytes"]["down"].items()},
                bytes_up={str(k): int(v) for k, v in entry["bytes"]["up"].items()},
            )
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise SettingsError(f"round history entry: bad or missing field ({exc})") from None


def fl_settings(
    setting: Setting,
    method: str,
    *,
    run_dir: str,
    out_dir: str,
    rounds: int,
    future_steps: int,
    stride: int,
    seed: int,
    field_m: tuple[float, float],
    epochs: int | None = None,
    **rest: object,
) -> FlSettings:
    """The Flower settings of ``method`` trained as ``setting`` says (its model and training
    sub-configs) for ``rounds`` rounds of windows L_p -> ``future_steps`` every ``stride``
    samples, seeded by ``seed``, in a field of ``field_m`` = (width, height) m; ``epochs``
    replaces the training's E (the closed loop's online rounds); ``rest`` are further
    :class:`FlSettings` fields (``labels``, ``train_fraction``, ``resume``, ``faults``, ...).
    SCAFFOLD's drift correction applies to FedAvg-based federated methods only: FedProx is an
    alternative to it, and methods trained in the cloud or alone have no drift to correct."""
    training, model = setting.training, setting.model
    spec = METHODS[method]
    drift = "none" if spec.proximal or not spec.federated else training.drift_correction
    return FlSettings(
        run_dir,
        out_dir,
        method=method,
        rounds=rounds,
        past_steps=model.past_steps,
        future_steps=future_steps,
        stride=stride,
        epochs=training.epochs if epochs is None else epochs,
        lr=training.lr,
        batch_size=training.batch_size,
        proximal_mu=training.proximal_mu,
        seed=seed,
        weights_dtype=training.weights_dtype,
        aggregation=training.aggregation,
        field_width=field_m[0],
        field_height=field_m[1],
        adain_sites=",".join(model.adain_sites),
        head_style_init=model.head_style_init,
        box_size=model.box_size,
        optimizer=training.optimizer,
        drift_correction=drift,
        lr_step_at=training.lr_step_at,
        **rest,  # type: ignore[arg-type]
    )


def online_settings(
    setting: Setting,
    method: str,
    seed: int,
    field_m: tuple[float, float],
    run_dir: str = "",
    out_dir: str = "",
) -> FlSettings:
    """The settings of a closed-loop episode's model updates, shared by ``dronefl track`` and
    the deployment's cloud: :func:`fl_settings` with the learning sub-config's windows (L_f =
    1, one every ``learning.stride`` samples) and E, the fused tracks as labels, every
    recorded window trained on (no test split, no federated evaluation) and a constant lr."""
    learning = setting.learning
    return replace(
        fl_settings(
            setting, method, run_dir=run_dir, out_dir=out_dir, rounds=1, future_steps=1,
            stride=learning.stride, seed=seed, field_m=field_m, epochs=learning.epochs,
            labels="tracks", train_fraction=1.0,
        ),
        lr_step_at=1.0,
    )  # fmt: skip
