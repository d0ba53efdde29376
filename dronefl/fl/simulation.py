"""Federated learning on Flower's simulation engine.

* :func:`run_federated` trains one method for a number of rounds (one engine start per call);
* :func:`run_session` keeps one engine up while ``body`` runs as the ServerApp, playing a
  round whenever it likes (the closed loop: one round per 100 s of an episode, each on the data
  recorded so far), so the engine's start-up (Ray, ~5 s) is paid once per episode.

The same ServerApp/ClientApp run in a deployment (SuperLink + one SuperNode per drone with
``--node-config "drone-id=<id>"``, run config = :meth:`FlSettings.to_run_config`).
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TypeVar

from flwr.app import Context
from flwr.server.superlink.fleet.vce.backend import Backend
from flwr.serverapp import Grid, ServerApp
from flwr.simulation import run_simulation

from dronefl.fl import TrainingError
from dronefl.fl.checkpoint import CheckpointError, load_checkpoint
from dronefl.fl.client_app import build_client_app
from dronefl.fl.records import FlSettings, RoundRecord
from dronefl.fl.server_app import RoundCallback, RoundDriver, build_server_app, num_drones

T = TypeVar("T")

# Ray starts its workers at nice 15 by default, so on a shared machine a federated run starves
# behind any other work; they run at the priority of the command that started them instead.
os.environ.setdefault("RAY_worker_niceness", "0")
# Ray's failure signal handler takes over SIGTERM in every process that starts Ray and dumps
# core on it (exit -6); without it, SIGTERM stops a run as Ctrl-C does (``dronefl.cli``).
os.environ.setdefault("RAY_DISABLE_FAILURE_SIGNAL_HANDLER", "1")
# When a run is killed (SIGKILL, OOM), Ray's dashboard and runtime-env agents report the dead
# raylet to the GCS, which died with it, and wait for it as long as a GCS client waits to
# reconnect: 60 s by default (measured: 61.7 s; with 20, 20.1 s). Every other process of the
# run is gone within about a second.
os.environ.setdefault("RAY_gcs_rpc_server_reconnect_timeout_s", "20")


#: Set once Ctrl-C has stopped a simulation engine in this process. Flower's engine then kills
#: its actors (:func:`_terminate`) but leaves Ray up and its worker threads (not daemons)
#: ending, so the interpreter cannot exit normally (``dronefl.cli.leave`` ends it).
ENGINE_INTERRUPTED = threading.Event()


def _interrupt(signum: int, frame: object) -> None:
    """Ctrl-C during a simulation: note it and silence Flower's logger, then interrupt as
    Python's default handler does. Flower's engine then shuts Ray down while its worker threads
    still wait on the ClientApp actors, and each logs the dead actor's traceback: the
    consequence of the interrupt, not news (``dronefl`` ends with one line and exit 130)."""
    ENGINE_INTERRUPTED.set()
    logging.getLogger("flwr").disabled = True
    signal.default_int_handler(signum, frame)


def _terminate(backend: Backend) -> None:
    """Flower's ``RayBackend.terminate``, made safe for Ctrl-C and quiet.

    The stock one asks only the idle ClientApp actors to stop (each then logs "Manually
    terminating ClientAppActor", which Ray forwards to the terminal when its log monitor gets
    there before the shutdown) and shuts Ray down at once. Interrupted, Flower's engine calls
    it while its worker threads still wait in ``ray.get`` on busy actors; a worker thread that
    touches Ray after the shutdown makes Ray end the whole process (exit code 1, "The core
    worker has already been shutdown") before ``dronefl`` can report the interrupt.

    This one kills every actor, idle or busy (no log), so each waiting thread gets an error at
    once and, the engine's stop event being set, ends. Without an interrupt it then shuts Ray
    down; after Ctrl-C (:data:`ENGINE_INTERRUPTED`) it leaves Ray up, and
    ``dronefl.cli.leave`` joins the threads and only then shuts Ray down."""
    import ray

    pool = backend.pool  # type: ignore[attr-defined]
    if pool is not None:
        busy = getattr(pool, "_future_to_actor", {}).values()
        for actor in [*pool.pool, *busy]:
            ray.kill(actor, no_restart=True)
    if not ENGINE_INTERRUPTED.is_set():
        ray.shutdown()


@contextmanager
def _interruptible_backend() -> Iterator[None]:
    """While open, Flower's Ray backend terminates through :func:`_terminate`, and
    ``ray.init`` keeps the process's SIGTERM handler (Ray's would end the process at once,
    with code 15, instead of stopping the run as Ctrl-C does). Ray is imported here, after
    this module has set Ray's environment variables."""
    import ray._private.utils as ray_utils
    from flwr.server.superlink.fleet.vce.backend.raybackend import RayBackend

    stock_terminate, stock_handler = RayBackend.terminate, ray_utils.set_sigterm_handler
    RayBackend.terminate = _terminate  # type: ignore[method-assign]
    ray_utils.set_sigterm_handler = lambda _handler: None
    try:
        yield
    finally:
        RayBackend.terminate = stock_terminate  # type: ignore[method-assign]
        ray_utils.set_sigterm_handler = stock_handler


def _run_engine(**kwargs: object) -> None:
    """``run_simulation(**kwargs)`` with :func:`_interruptible_backend`, noting a Ctrl-C in
    :data:`ENGINE_INTERRUPTED`. The Ctrl-C handler is only replaced where Python's own is
    installed (in the main thread): a process that inherited SIGINT ignored keeps ignoring it."""
    previous = signal.getsignal(signal.SIGINT)
    ours = previous is signal.default_int_handler
    ours = ours and threading.current_thread() is threading.main_thread()
    if ours:
        signal.signal(signal.SIGINT, _interrupt)
    try:
        with _interruptible_backend():
            run_simulation(**kwargs)  # type: ignore[arg-type]
    except KeyboardInterrupt:
        ENGINE_INTERRUPTED.set()
        raise
    finally:
        if ours:
            signal.signal(signal.SIGINT, previous)


#: Environment variable: how many Ray workers (one CPU each) the simulation engine starts.
WORKERS_ENV = "DRONEFL_SIM_WORKERS"


def sim_workers() -> int:
    """Ray workers of the simulation engine: ``$DRONEFL_SIM_WORKERS``, else 2 (two drones'
    trainings side by side on a 2-core machine). Each worker imports torch and the ClientApp
    at every engine start (measured: a second worker costs about 5 CPU-s per start); the test
    suite, which runs tests in parallel, sets 1. The results do not depend on it: each drone's
    training is seeded by its drone id and round."""
    value = os.environ.get(WORKERS_ENV, "2")
    if not value.isdigit() or int(value) < 1:
        raise ValueError(f"{WORKERS_ENV}: must be a whole number >= 1, got {value!r}")
    return int(value)


#: Ray resources: ``num_cpus`` workers of one CPU each, a small object store, no dashboard.
def backend_config(num_cpus: int | None = None) -> dict:
    """Backend configuration for ``run_simulation``: ``num_cpus`` Ray workers of 1 CPU
    (default :func:`sim_workers`)."""
    return {
        "client_resources": {"num_cpus": 1, "num_gpus": 0.0},
        "init_args": {
            "num_cpus": num_cpus or sim_workers(),
            "num_gpus": 0,
            "include_dashboard": False,
            "object_store_memory": 100 * 1024 * 1024,
        },
    }


def run_federated(
    settings: FlSettings, on_round: RoundCallback | None = None, num_cpus: int | None = None
) -> list[RoundRecord]:
    """Train ``settings.method`` for ``settings.rounds`` rounds on the simulation engine and
    return the round history (also in ``settings.history_path``).

    Raises :class:`TrainingError` if the run stopped early or if a round accepted no drone's update
    (every reply failed or was left out): the rounds are in the history and the checkpoint,
    but a model that missed a whole round is not the model the run was asked for."""
    config = settings.to_run_config()
    with _quiet_flower():
        _run_engine(
            server_app=build_server_app(config, on_round),
            client_app=build_client_app(config),
            num_supernodes=num_drones(settings.run_dir),
            backend_config=backend_config(num_cpus),
        )
    try:
        checkpoint = load_checkpoint(
            settings.checkpoint_path, settings.history_path, settings.method
        )
    except CheckpointError as exc:
        raise TrainingError(f"federated run of {settings.method} wrote no result: {exc}") from None
    if checkpoint.server_round < settings.rounds:
        raise TrainingError(
            f"federated run of {settings.method} stopped after round {checkpoint.server_round} "
            f"of {settings.rounds}; see the log above (resume with --resume)"
        )
    for entry in checkpoint.history:
        if not entry.train_loss:
            why = "; ".join(entry.rejected) or "no drone was asked"
            raise TrainingError(
                f"federated run of {settings.method}: round {entry.server_round} accepted no "
                f"update, so the global model did not train ({why})"
            )
    return checkpoint.history


def run_session(
    settings: FlSettings,
    n_drones: int,
    body: Callable[[RoundDriver], T],
    num_cpus: int | None = None,
) -> T:
    """Start the simulation engine with ``n_drones`` SuperNodes, run ``body(driver)`` as the
    ServerApp and return its result; ``driver.play(state, round, run_dir=...)`` plays a round
    on the drones' data in ``run_dir``. An exception in ``body`` is raised here once the engine
    has stopped."""
    outcome: dict[str, T] = {}
    failure: list[BaseException] = []
    app = ServerApp()

    @app.main()
    def main(grid: Grid, context: Context) -> None:
        try:
            outcome["result"] = body(RoundDriver(grid, settings, n_drones))
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
            failure.append(exc)

    with _quiet_flower():
        _run_engine(
            server_app=app,
            client_app=build_client_app(settings.to_run_config()),
            num_supernodes=n_drones,
            backend_config=backend_config(num_cpus),
        )
    if failure:
        raise failure[0]
    if "result" not in outcome:
        raise RuntimeError("the federated session ended without a result; see the log above")
    return outcome["result"]


@contextmanager
def _quiet_flower() -> Iterator[None]:
    """No telemetry or Ray log deduplication, and Flower's logger at ERROR: ``run_simulation``
    warns on every call that ``flwr run`` is preferred; failed rounds are reported by the
    strategy and by the callers' checks."""
    os.environ.setdefault("FLWR_TELEMETRY_ENABLED", "0")
    os.environ.setdefault("RAY_DEDUP_LOGS", "0")
    os.environ.setdefault("RAY_ACCEL_ENV_VAR_OVERRIDE_ON_ZERO", "0")
    flwr_logger = logging.getLogger("flwr")
    level = flwr_logger.level
    flwr_logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        flwr_logger.setLevel(level)
