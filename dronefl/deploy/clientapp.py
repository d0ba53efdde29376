"""The drone's ClientApp in a deployment: the simulation's training, on the drone's own disk.

Training is :func:`dronefl.fl.client_app.handle_train` unchanged; only where the data lies
differs: the SuperNode's node config names the drone (``drone-id``) and its data folder
(``data-dir``), where the drone process writes its onboard record (``drone_<id>.npz``) and
the round's pseudo-labels (``tracks.npz``) before each round.

The Deployment Engine runs every message in a fresh process, so the new global model of a
round reaches the drone's predictor through the disk: a ``query`` message carrying the
weights makes this app write them, with the run's architecture, to ``<data-dir>/global.npz``.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from flwr.app import Context, Message, MetricRecord, RecordDict
from flwr.clientapp import ClientApp

from dronefl.fl.client_app import handle_train
from dronefl.fl.records import (
    ARRAYS_KEY,
    DRONE_KEY,
    METRICS_KEY,
    ROUND_KEY,
    FlSettings,
    SettingsError,
)
from dronefl.io import atomic_savez
from dronefl.models.model import PredictorConfig

DATA_DIR_KEY = "data-dir"
GLOBAL_MODEL = "global.npz"

#: Names of the round number and of the architecture (JSON) inside a model file.
_ROUND = "__server_round__"
_MODEL = "__model__"

app = ClientApp()


@dataclass(frozen=True)
class SavedModel:
    """A model file's content: the weights ``state``, the ``server_round`` they are of (0:
    pretrained) and the architecture ``model`` they belong to."""

    state: dict[str, torch.Tensor]
    server_round: int
    model: PredictorConfig


def save_model(
    path: Path, state: dict[str, torch.Tensor], server_round: int, model: PredictorConfig
) -> None:
    """Write model weights (after ``server_round``; 0: pretrained) and their architecture
    ``model`` atomically to ``path``: the file alone says how to build the predictor (a
    setting's box reading changes the model, not the shapes of its weights)."""
    arrays = {k: v.detach().cpu().numpy() for k, v in state.items()}
    atomic_savez(
        path, **{_ROUND: np.array(server_round), _MODEL: np.array(model.to_json())}, **arrays
    )


def load_model(path: Path) -> SavedModel:
    """The content of a file written by :func:`save_model`; ``FileNotFoundError`` naming the
    file when it is missing, corrupt or records no architecture."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            names = [k for k in npz.files if k not in (_ROUND, _MODEL)]
            state = {k: torch.from_numpy(npz[k].copy()) for k in names}
            model = PredictorConfig.from_json(str(npz[_MODEL]))
            return SavedModel(state, int(npz[_ROUND]), model)
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise FileNotFoundError(f"{path}: missing or corrupt model file ({exc})") from None


def drone_settings(context: Context) -> FlSettings:
    """The run's settings with this drone's data folder as run and output folder."""
    config = dict(context.node_config)
    for key in (DRONE_KEY, DATA_DIR_KEY):
        if key not in config:
            raise SettingsError(f"node config: missing {key!r} (set by `dronefl drone`)")
    settings = FlSettings.from_run_config(dict(context.run_config))
    folder = str(config[DATA_DIR_KEY])
    return replace(settings, run_dir=folder, out_dir=folder)


@app.train()
def train(msg: Message, context: Context) -> Message:
    return handle_train(msg, context, drone_settings(context))


@app.query()
def query(msg: Message, context: Context) -> Message:
    """Install the global model sent on this drone's disk; answer the drone id."""
    settings = drone_settings(context)
    drone_id = int(context.node_config[DRONE_KEY])
    state = settings.layout.unpack(msg.content[ARRAYS_KEY])
    server_round = int(msg.content["config"][ROUND_KEY])
    save_model(Path(settings.run_dir) / GLOBAL_MODEL, state, server_round, settings.model)
    reply = RecordDict({METRICS_KEY: MetricRecord({DRONE_KEY: drone_id})})
    return Message(content=reply, reply_to=msg)
