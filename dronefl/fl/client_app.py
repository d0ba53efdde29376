"""The drone side of federated learning: a Flower ``ClientApp`` (Message API).

On ``train`` a drone loads the global weights (one flat vector, see
:class:`dronefl.fl.records.WeightLayout`), trains E epochs on its own windows
(:func:`dronefl.models.train.train_local`, with FedProx's proximal term when the strategy sent
``proximal-mu``) and replies with its weights and sample count. On ``evaluate`` it reports the
test MSE of the global model on its held-out (later) windows. FedPer drones keep the output
head in ``context.state`` and never send it. With SCAFFOLD (``drift-correction``) a drone
keeps its control variate c_i in ``context.state``, steps along ``g_i - c_i + c`` with the
cloud's c received beside the weights, and sends its new c_i beside its weights. What a drone
keeps also goes to its disk (``<out>/personal``, ``<out>/control``), for a resumed run.

Which drone a node is: ``node_config["drone-id"]`` in a deployment, else the
``partition-id``-th drone of the recorded run (simulation). Settings come from the run config
(:class:`dronefl.fl.records.FlSettings`); ``app`` is the deployable object
(``dronefl.fl.client_app:app``).
"""

from __future__ import annotations

from dataclasses import replace
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from flwr.app import Context, Message, RecordDict
from flwr.clientapp import ClientApp

from dronefl.fl.faults import inject
from dronefl.fl.records import (
    ARRAYS_KEY,
    CONFIG_KEY,
    CONTROL_KEY,
    DRONE_KEY,
    METRICS_KEY,
    PARTITION_KEY,
    PERSONAL_KEY,
    ClientReport,
    FlSettings,
    SettingsError,
    TrainInstructions,
    to_arrays,
    to_state,
)
from dronefl.fl.watchdog import exit_with_parent
from dronefl.io import atomic_savez
from dronefl.models.model import TrajectoryTransformer, build_model
from dronefl.models.train import (
    TrainStats,
    drift_correction,
    evaluate,
    local_steps,
    proximal_term,
    train_local,
    updated_control_variate,
)
from dronefl.models.windows import WindowSet, WindowSpec, load_drone_split


def build_client_app(defaults: dict | None = None) -> ClientApp:
    """A ClientApp whose settings are ``defaults`` overridden by the run config.

    The simulation passes the experiment's settings as ``defaults`` (Flower's
    ``run_simulation`` takes no run config); a deployment passes them as the run config.
    """
    app = ClientApp()

    @app.train()
    def train(msg: Message, context: Context) -> Message:
        return handle_train(msg, context, _settings(context, defaults))

    @app.evaluate()
    def evaluate_(msg: Message, context: Context) -> Message:
        return handle_evaluate(msg, context, _settings(context, defaults))

    return app


def handle_train(msg: Message, context: Context, settings: FlSettings) -> Message:
    """One round of local training on this drone."""
    settings, instructions, drone_id = _round_context(msg, context, settings)
    server_round = instructions.server_round
    train_set, _ = _windows(settings.run_dir, drone_id, settings.windows, settings.labels)
    layout = settings.layout
    global_state = layout.unpack(msg.content[ARRAYS_KEY])
    model = _local_model(settings, global_state, context, drone_id, server_round)
    regularizer = None
    if instructions.proximal_mu > 0:
        regularizer = proximal_term(global_state, instructions.proximal_mu)
    if settings.scaffold:
        server_control = layout.unpack_control(msg.content[ARRAYS_KEY])
        control = _kept(context, CONTROL_KEY, _control_path(settings, drone_id, server_round - 1))
        control = layout.zeros() if control is None else control
        regularizer = drift_correction(server_control, control)
    config = settings.train_config(server_round, drone_id)
    if len(train_set) == 0:  # no labelled window (yet): the server leaves this drone out
        stats = TrainStats(0, float("nan"), 0.0)
    else:
        stats = train_local(model, train_set, config, regularizer)
    state = model.state_dict()
    if settings.method_spec.personal:
        head = {k: v for k, v in state.items() if k.startswith(TrajectoryTransformer.HEAD)}
        _keep(context, PERSONAL_KEY, _personal_path(settings, drone_id), head)
        state = {k: v for k, v in state.items() if k in global_state}
    if settings.scaffold and stats.num_examples > 0:
        steps = local_steps(stats.num_examples, config)
        control = updated_control_variate(
            control, server_control, global_state, state, steps, config
        )
        _keep(context, CONTROL_KEY, _control_path(settings, drone_id, server_round), control)
        _control_path(settings, drone_id, server_round - 2).unlink(missing_ok=True)
    report = ClientReport(drone_id, stats.num_examples, stats.loss)
    arrays = layout.pack(state, control if settings.scaffold else None)
    content = RecordDict({ARRAYS_KEY: arrays, METRICS_KEY: report.to_metrics()})
    content = inject(settings, instructions.server_round, drone_id, content)
    return Message(content=content, reply_to=msg)


def handle_evaluate(msg: Message, context: Context, settings: FlSettings) -> Message:
    """Test MSE (m^2) of the global model (with this drone's personal head, for FedPer)."""
    settings, instructions, drone_id = _round_context(msg, context, settings)
    _, test_set = _windows(settings.run_dir, drone_id, settings.windows, settings.labels)
    global_state = settings.layout.unpack(msg.content[ARRAYS_KEY])
    model = _local_model(settings, global_state, context, drone_id, instructions.server_round)
    report = ClientReport(drone_id, len(test_set), evaluate(model, test_set))
    content = RecordDict({METRICS_KEY: report.to_metrics()})
    content = inject(settings, instructions.server_round, drone_id, content)
    return Message(content=content, reply_to=msg)


def _local_model(
    settings: FlSettings,
    global_state: dict[str, torch.Tensor],
    context: Context,
    drone_id: int,
    server_round: int,
) -> TrajectoryTransformer:
    """The model with the global weights, plus the personal head for FedPer (the seeded
    initial head in the first round)."""
    model = build_model(settings.model, seed=settings.seed)
    if not settings.method_spec.personal:
        model.load_state_dict(global_state)
        return model
    state = model.state_dict()
    state.update(global_state)
    head = _personal(context, settings, drone_id, server_round)
    if head is not None:
        state.update(head)
    model.load_state_dict(state)
    return model


def _personal(
    context: Context, settings: FlSettings, drone_id: int, server_round: int
) -> dict[str, torch.Tensor] | None:
    if server_round == 1 and PERSONAL_KEY not in context.state:
        return None
    return _kept(context, PERSONAL_KEY, _personal_path(settings, drone_id))


def _kept(context: Context, key: str, path: Path) -> dict[str, torch.Tensor] | None:
    """What this drone kept under ``key``: from ``context.state``, or, in a resumed run (which
    starts with an empty context), from its copy at ``path``; None if it kept nothing."""
    if key in context.state:
        return to_state(context.state[key])
    if path.is_file():
        with np.load(path, allow_pickle=False) as npz:
            return {k: torch.from_numpy(npz[k].copy()) for k in npz.files}
    return None


def _keep(context: Context, key: str, path: Path, state: dict[str, torch.Tensor]) -> None:
    """Keep ``state`` under ``key`` in ``context.state`` and atomically at ``path``."""
    context.state[key] = to_arrays(state)
    atomic_savez(path, **{k: v.numpy() for k, v in state.items()})


def _personal_path(settings: FlSettings, drone_id: int) -> Path:
    return Path(settings.out_dir) / "personal" / f"drone_{drone_id}.npz"


def _control_path(settings: FlSettings, drone_id: int, server_round: int) -> Path:
    """The drone's control variate after ``server_round`` (by round, so that a run killed
    after the drones' round but before the cloud's checkpoint resumes with the one it had)."""
    return Path(settings.out_dir) / "control" / f"drone_{drone_id}_round_{server_round}.npz"


def _settings(context: Context, defaults: dict | None) -> FlSettings:
    return FlSettings.from_run_config({**(defaults or {}), **dict(context.run_config)})


def _round_context(
    msg: Message, context: Context, settings: FlSettings
) -> tuple[FlSettings, TrainInstructions, int]:
    """The cloud's instructions for this round, the settings with the round's data folder
    (when the cloud named one) and this node's drone id; one torch thread per drone, and
    the process ends if the one that started it dies (:mod:`dronefl.fl.watchdog`)."""
    exit_with_parent()
    torch.set_num_threads(1)
    instructions = TrainInstructions.from_config(msg.content[CONFIG_KEY])
    if instructions.run_dir is not None:
        settings = replace(settings, run_dir=instructions.run_dir)
    return settings, instructions, _drone_id(context, settings)


def _drone_id(context: Context, settings: FlSettings) -> int:
    config = dict(context.node_config)
    if DRONE_KEY in config:
        return int(config[DRONE_KEY])
    if PARTITION_KEY not in config:
        raise SettingsError(f"node config: needs {DRONE_KEY!r} or {PARTITION_KEY!r}")
    drones = sorted(int(p.stem.split("_")[1]) for p in Path(settings.run_dir).glob("drone_*.npz"))
    partition = int(config[PARTITION_KEY])
    if not 0 <= partition < len(drones):
        raise SettingsError(
            f"node config: partition {partition} but the run has {len(drones)} drones"
        )
    return drones[partition]


@lru_cache(maxsize=8)
def _windows(
    run_dir: str, drone_id: int, spec: WindowSpec, labels: str
) -> tuple[WindowSet, WindowSet]:
    """This drone's train/test windows, loaded once per process."""
    return load_drone_split(run_dir, drone_id, spec, labels)


app = build_client_app()
