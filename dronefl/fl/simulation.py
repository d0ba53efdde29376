"""Run one federated method on Flower's simulation engine (one Ray start per run).

The same ServerApp/ClientApp run in a deployment (SuperLink + one SuperNode per drone with
``--node-config "drone-id=<id>"``, run config = :meth:`FlSettings.to_run_config`).
"""

from __future__ import annotations

import logging
import os

from flwr.simulation import run_simulation

from dronefl.fl.checkpoint import CheckpointError, load_checkpoint
from dronefl.fl.client_app import build_client_app
from dronefl.fl.records import FlSettings
from dronefl.fl.server_app import RoundCallback, build_server_app, num_drones


#: Ray resources: two workers, one CPU each (the two drones' trainings run side by side),
#: a small object store, no dashboard. Sized for a 2-core, 24 GiB machine.
def backend_config(num_cpus: int = 2) -> dict:
    """Backend configuration for ``run_simulation``: ``num_cpus`` Ray workers of 1 CPU."""
    return {
        "client_resources": {"num_cpus": 1, "num_gpus": 0.0},
        "init_args": {
            "num_cpus": num_cpus,
            "num_gpus": 0,
            "include_dashboard": False,
            "object_store_memory": 100 * 1024 * 1024,
        },
    }


def run_federated(
    settings: FlSettings, on_round: RoundCallback | None = None, num_cpus: int = 2
) -> list[dict]:
    """Train ``settings.method`` for ``settings.rounds`` rounds on the simulation engine and
    return the round history (also in ``settings.history_path``)."""
    os.environ.setdefault("FLWR_TELEMETRY_ENABLED", "0")
    os.environ.setdefault("RAY_DEDUP_LOGS", "0")
    os.environ.setdefault("RAY_ACCEL_ENV_VAR_OVERRIDE_ON_ZERO", "0")
    config = settings.to_run_config()
    flwr_logger = logging.getLogger("flwr")
    level = flwr_logger.level
    # ERROR: run_simulation warns on every call that `flwr run` is preferred; failed rounds are
    # reported by the strategy and by the checks below.
    flwr_logger.setLevel(logging.ERROR)
    try:
        run_simulation(
            server_app=build_server_app(config, on_round),
            client_app=build_client_app(config),
            num_supernodes=num_drones(settings.run_dir),
            backend_config=backend_config(num_cpus),
        )
    finally:
        flwr_logger.setLevel(level)
    try:
        checkpoint = load_checkpoint(
            settings.checkpoint_path, settings.history_path, settings.method
        )
    except CheckpointError as exc:
        raise RuntimeError(f"federated run of {settings.method} wrote no result: {exc}") from None
    if checkpoint.server_round < settings.rounds:
        raise RuntimeError(
            f"federated run of {settings.method} stopped after round {checkpoint.server_round} "
            f"of {settings.rounds}; see the log above (resume with --resume)"
        )
    return checkpoint.history
