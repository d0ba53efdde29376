"""The cloud side of federated learning: a Flower ``ServerApp`` (Message API).

:func:`run_server` builds the method's initial global model (seeded; resumed from
``checkpoint.npz`` with ``resume``), wraps the Grid in a byte counter, and hands the round
loop to the method's strategy. After every round it records the round (per-drone test MSE
and their mean, training losses, rejected updates, bytes down/up) and writes the checkpoint
and history atomically. ``app`` is the deployable object (``dronefl.fl.server_app:app``).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from flwr.app import ArrayRecord, Context, MetricRecord
from flwr.serverapp import Grid, ServerApp

from dronefl.fl.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from dronefl.fl.comm import CountingGrid
from dronefl.fl.records import FlSettings, SettingsError, to_arrays, to_state
from dronefl.fl.strategies import make_strategy
from dronefl.models.model import TrajectoryTransformer, build_model

#: Called with each finished round's history entry (e.g. to advance a progress bar).
RoundCallback = Callable[[dict], None]


def build_server_app(
    defaults: dict | None = None, on_round: RoundCallback | None = None
) -> ServerApp:
    """A ServerApp whose settings are ``defaults`` overridden by the run config."""
    app = ServerApp()

    @app.main()
    def main(grid: Grid, context: Context) -> None:
        settings = FlSettings.from_run_config({**(defaults or {}), **dict(context.run_config)})
        run_server(grid, settings, on_round)

    return app


def num_drones(run_dir: str | Path) -> int:
    """Number of drone logs in a recorded run folder."""
    n = len(list(Path(run_dir).glob("drone_*.npz")))
    if n == 0:
        raise SettingsError(f"run-dir: {run_dir} holds no drone_<id>.npz logs")
    return n


def initial_state(settings: FlSettings) -> dict:
    """The seeded initial global weights (without the personal head for FedPer)."""
    state = build_model(settings.model, seed=settings.seed).state_dict()
    if settings.method_spec.personal:
        state = {k: v for k, v in state.items() if not k.startswith(TrajectoryTransformer.HEAD)}
    return state


def run_server(
    grid: Grid, settings: FlSettings, on_round: RoundCallback | None = None
) -> list[dict]:
    """Run (or resume) ``settings.rounds`` global rounds; returns the round history."""
    state, offset, history = initial_state(settings), 0, []
    if settings.resume and settings.checkpoint_path.is_file():
        checkpoint = load_checkpoint(
            settings.checkpoint_path, settings.history_path, settings.method
        )
        state, offset, history = checkpoint.state, checkpoint.server_round, checkpoint.history
    remaining = settings.rounds - offset
    if remaining <= 0:
        return history
    strategy = make_strategy(
        settings.method_spec, num_drones(settings.run_dir), settings.proximal_mu, offset
    )
    counting = CountingGrid(grid)

    def end_of_round(local_round: int, arrays: ArrayRecord) -> MetricRecord | None:
        if local_round == 0:  # Flower also calls this before the first round
            return None
        server_round = local_round + offset
        log = strategy.logs[server_round]
        entry = {
            "round": server_round,
            "mean_test_mse": log.mean_test_mse,
            "test_mse": {str(k): v for k, v in sorted(log.test_mse.items())},
            "train_loss": {str(k): v for k, v in sorted(log.train_loss.items())},
            "rejected": log.rejected,
            "bytes": counting.traffic.of_round(server_round),
        }
        history.append(entry)
        save_checkpoint(
            settings.checkpoint_path,
            settings.history_path,
            Checkpoint(settings.method, server_round, to_state(arrays), history),
        )
        if on_round is not None:
            on_round(entry)
        return None

    strategy.start(counting, to_arrays(state), num_rounds=remaining, evaluate_fn=end_of_round)
    return history


app = build_server_app()
