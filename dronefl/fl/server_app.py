"""The cloud side of federated learning: a Flower ``ServerApp`` (Message API).

:func:`run_server` builds the method's initial global model (seeded; resumed from
``checkpoint.npz`` with ``resume``) and plays the rounds with a :class:`RoundDriver`: it wraps
the Grid in a byte counter, hands the round loop to the method's strategy, and after every
round records it (per-drone test MSE and their mean, training losses, rejected updates, bytes
down/up) and writes the checkpoint and history atomically. The closed loop keeps one driver
for a whole episode and plays one round at a time on new data
(:func:`dronefl.fl.simulation.run_session`). ``app`` is the deployable object
(``dronefl.fl.server_app:app``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

import torch
from flwr.app import ArrayRecord, ConfigRecord, Context, Message, MetricRecord
from flwr.serverapp import Grid, ServerApp

from dronefl.fl.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from dronefl.fl.records import RUN_DIR_KEY, FlSettings, RoundRecord, SettingsError, global_part
from dronefl.fl.strategies import make_strategy
from dronefl.fl.traffic import CountingGrid, Traffic
from dronefl.io import crash_point
from dronefl.models.model import build_model

#: The longest the first exchange with the drones may take (their start-up), s.
STARTUP_TIMEOUT = 3600.0
#: Called with each finished round (e.g. to advance a progress bar).
RoundCallback = Callable[[RoundRecord], None]


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


def initial_state(settings: FlSettings) -> dict[str, torch.Tensor]:
    """The seeded initial global weights (without the personal head for FedPer)."""
    return global_part(build_model(settings.model, seed=settings.seed).state_dict(), settings)


def run_server(
    grid: Grid, settings: FlSettings, on_round: RoundCallback | None = None
) -> list[RoundRecord]:
    """Run (or resume) ``settings.rounds`` global rounds; returns the round history."""
    state, offset, history, control = initial_state(settings), 0, [], None
    if settings.resume and settings.checkpoint_path.is_file():
        checkpoint = load_checkpoint(
            settings.checkpoint_path, settings.history_path, settings.method, like=state
        )
        state, offset, history = checkpoint.state, checkpoint.server_round, checkpoint.history
        control = checkpoint.control
    remaining = settings.rounds - offset
    if remaining <= 0:
        return history
    driver = RoundDriver(grid, settings, num_drones(settings.run_dir), history, control)
    driver.play(state, offset + 1, remaining, on_round=on_round)
    return driver.history


class StartupGrid:
    """A Grid whose first exchange waits up to :data:`STARTUP_TIMEOUT` s whatever the round
    timeout: the drones' first answer includes starting their ClientApps (importing torch,
    loading data), which can take longer than a round; later exchanges keep the strategy's
    timeout (``round_timeout``)."""

    def __init__(self, grid: Grid) -> None:
        self._grid = grid
        self._started = False

    def __getattr__(self, name: str) -> object:
        return getattr(self._grid, name)

    def send_and_receive(
        self, messages: Iterable[Message], *, timeout: float | None = None
    ) -> Iterable[Message]:
        if not self._started:
            timeout = max(timeout or 0.0, STARTUP_TIMEOUT)
        replies = self._grid.send_and_receive(messages, timeout=timeout)
        self._started = True
        return replies


class RoundDriver:
    """Plays global rounds of ``settings.method`` with ``n_drones`` drones through ``grid``.

    Each round's entry is appended to :attr:`history` and the checkpoint and history are
    written atomically to ``settings.out_dir``. Weights travel as
    :meth:`FlSettings.layout` says (one flat fp32 or fp16 vector); :attr:`traffic` holds the
    bytes of every message, by round and message type. With SCAFFOLD, :attr:`control` is the
    cloud's control variate c (zeros at the start, or ``control``), sent beside the weights;
    Flower's sample-weighted mean of the drones' c_i becomes the next c, and it is
    checkpointed with the weights.
    """

    def __init__(
        self,
        grid: Grid,
        settings: FlSettings,
        n_drones: int,
        history: list[RoundRecord] | None = None,
        control: dict[str, torch.Tensor] | None = None,
    ) -> None:
        self.settings = settings
        self.n_drones = n_drones
        self.history: list[RoundRecord] = list(history or [])
        self.layout = settings.layout
        self.control: dict[str, torch.Tensor] | None = None
        if settings.scaffold:
            self.control = self.layout.zeros() if control is None else control
        self._grid = CountingGrid(StartupGrid(grid))

    @property
    def traffic(self) -> Traffic:
        """Bytes of every message sent and received so far."""
        return self._grid.traffic

    def play(
        self,
        state: dict[str, torch.Tensor],
        first_round: int,
        n_rounds: int = 1,
        run_dir: str | None = None,
        on_round: RoundCallback | None = None,
    ) -> dict[str, torch.Tensor]:
        """Play global rounds ``first_round .. first_round + n_rounds - 1`` from the global
        weights ``state``; the drones train on ``run_dir`` when given (else the run config's).
        Returns the new global weights (fp32)."""
        settings = self.settings
        strategy = make_strategy(
            settings.method_spec,
            self.n_drones,
            settings.proximal_mu,
            first_round - 1,
            evaluate=settings.evaluates,
            aggregation=settings.aggregation,
        )
        config = ConfigRecord({RUN_DIR_KEY: run_dir} if run_dir else {})
        latest = dict(state)

        def end_of_round(local_round: int, arrays: ArrayRecord) -> MetricRecord | None:
            if local_round == 0:  # Flower also calls this before the first round
                return None
            server_round = local_round + first_round - 1
            crash_point(f"round-end:{server_round}")
            entry = strategy.logs[server_round].record(self.traffic.of_round(server_round))
            self.history.append(entry)
            latest.update(self.layout.unpack(arrays))
            if self.control is not None:
                self.control = self.layout.unpack_control(arrays)
            save_checkpoint(
                settings.checkpoint_path,
                settings.history_path,
                Checkpoint(settings.method, server_round, dict(latest), self.history, self.control),
            )
            if on_round is not None:
                on_round(entry)
            return None

        strategy.start(
            self._grid,
            self.layout.pack(state, self.control),
            num_rounds=n_rounds,
            train_config=config,
            evaluate_config=ConfigRecord(dict(config)),
            evaluate_fn=end_of_round,
            timeout=settings.round_timeout,
        )
        return latest


app = build_server_app()
