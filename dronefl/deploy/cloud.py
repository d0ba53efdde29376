"""The cloud's ServerApp in a deployment: fusion, planning and FL rounds (SPEC §11).

Launched by ``flwr run`` against the SuperLink (``dronefl cloud``), it runs the episode's
cloud side step by step, locked to the world's clock:

1. wait for the world's telemetry of step ``k`` (every drone's autopilot state);
2. wait for the drones' predictions of step ``k`` until all live drones have sent theirs or
   ``deadline_ms`` of wall time have passed since the telemetry; a drone that missed it is
   *silent* this step (counted per drone);
3. fuse what arrived (one adaptive EKF per target), plan every drone's acceleration and send
   each its control (:class:`~dronefl.wire.ControlMessage`);
4. every ``fl_period`` s of simulated time (method ``dronefl``), play one FL round through the
   SuperLink while the world waits: each live drone writes its onboard record and the fused
   tracks (sent over Zenoh) to its disk, trains there (:mod:`dronefl.deploy.clientapp`), the
   cloud averages the updates (:class:`~dronefl.fl.server_app.RoundDriver`, the simulation's
   round), sends the new global model back through the SuperLink and has each drone load it;
5. release step ``k``: the world applies the controls and moves on.

The outputs are ``cloud.npz`` (per-step arrays) and ``cloud.json`` (rounds, bytes, silent
steps, timings) in ``out``; :mod:`dronefl.deploy.results` joins them with the world's truth.
"""

from __future__ import annotations

import threading
import time
from dataclasses import asdict, dataclass, field, replace
from logging import INFO, WARNING
from pathlib import Path

import numpy as np
import torch
from flwr.app import ConfigRecord, Context, Message, RecordDict
from flwr.common.logger import log
from flwr.serverapp import Grid, ServerApp

from dronefl.accounting import DIRECTIONS, ByteCounter
from dronefl.config import Scenario, load_scenario
from dronefl.deploy import DEPLOY_METHODS, CloudError
from dronefl.deploy.certs import CertificateFolder
from dronefl.deploy.clientapp import load_model
from dronefl.deploy.grid import DroneGrid
from dronefl.deploy.link import (
    CONTROL,
    FLUSH,
    NODE,
    PREDICTIONS,
    RELEASE,
    RELOAD,
    TELEMETRY,
    Link,
    LinkConfig,
)
from dronefl.deploy.messages import LabelsMessage, TelemetryMessage, encode_release
from dronefl.deploy.results import CloudLog, DeployedRound, TrafficCount
from dronefl.fl.records import ARRAYS_KEY, PRESETS, ROUND_KEY, FlSettings, RoundRecord
from dronefl.fl.server_app import RoundDriver
from dronefl.fl.traffic import message_bytes
from dronefl.io import atomic_savez
from dronefl.planning import DISTANCE_POINTS, DroneFLPlanner, PlannerConfig
from dronefl.tracking import Fuser, PositionMeasurement, fusion_config, make_labels
from dronefl.tracking.fusion import (
    CONSTANT_SPEED_PSD,
    COVERAGE_NOISE_PROFILE,
    NOISE_SPLITS,
    TEMPORAL_KERNEL,
    check_track_psd,
    constant_speed_q,
    fusion_record,
    planner_filter_config,
    planner_forecast,
    update_filters,
)
from dronefl.tracking.labels import LABEL_DRONES, training_labels
from dronefl.validation import check_one_of
from dronefl.wire import (
    ControlMessage,
    NoiseReportMessage,
    PredictionMessage,
    WireError,
    split_uplink,
)

#: How long a round waits for a live drone's SuperNode to connect (a restarted drone), s.
SUPERNODE_JOIN_S = 30.0

_PREFIX = "deploy-"


@dataclass(frozen=True)
class CloudSettings:
    """The cloud's side of one deployed episode (passed as the ServerApp's run config).

    ``deadline_ms`` wall ms the cloud waits for a step's predictions; ``start_timeout`` s
    for the world, the drones and their SuperNodes to appear; ``round_timeout`` s for one FL
    message exchange; ``tls_dir`` the certificate folder (empty: no TLS); ``model`` the
    pretrained weights (a file written by :func:`~dronefl.deploy.clientapp.save_model`);
    ``out`` where ``cloud.npz`` / ``cloud.json`` go; ``label_drones`` which drone learns from
    which label (:data:`~dronefl.tracking.labels.LABEL_DRONES`, as ``dronefl track
    --label-drones``); ``deshrink_labels`` pushes each drone's labels away from it by the pull
    its predictions show (as ``dronefl track --deshrink-labels``); ``preset`` the training
    setting of the rounds (a key of :data:`~dronefl.fl.records.PRESETS`, as ``dronefl track
    --config``; the rounds' own settings travel as :class:`~dronefl.fl.records.FlSettings`);
    ``noise_split`` the fusion's (as ``dronefl track --noise-split``: ``reported`` uses the
    noise reports that follow each drone's predictions); ``detected_only``: the drones send
    only the predictions of targets they detect (``dronefl drone --detected-only``), so a
    drone's own condition in ``--label-drones`` is that it watches the target (as ``dronefl
    track --detected-only``); ``planner_distance`` where the planner measures a drone
    (:attr:`~dronefl.planning.PlannerConfig.distance_at`, as ``dronefl track
    --planner-distance``); ``constant_speed_psd`` the fusion's process noise q for
    constant-speed targets, m^2/s^3 (as ``dronefl track --constant-speed-psd``); ``track_psd``
    the q of a second filter whose tracks the planner flies on, the labels smoothed from the
    fusion's own (as ``dronefl track --track-psd``; ``None``: one filter; ``deploy up`` passes
    the q its setting resolves to for the scenario); ``coverage_noise``: scale ``R`` of a
    prediction made from a window with few detections (as ``dronefl track --coverage-noise``);
    ``temporal_kernel``: the tracks the planner flies on are the temporal kernel's (as
    ``dronefl track --temporal-kernel``).
    """

    scenario: str
    model: str
    out: str
    method: str = "dronefl"
    duration: float = 120.0
    fl_period: float = 40.0
    deadline_ms: float = 150.0
    listen: str = "127.0.0.1:7441"
    connect: str = "127.0.0.1:7440"
    tls_dir: str = ""
    start_timeout: float = 120.0
    round_timeout: float = 300.0
    label_drones: str = "all"
    deshrink_labels: bool = False
    preset: str = "ours"
    noise_split: str = "adaptive"
    detected_only: bool = False
    planner_distance: str = "next"
    constant_speed_psd: float = CONSTANT_SPEED_PSD
    track_psd: float | None = None
    coverage_noise: bool = False
    temporal_kernel: bool = False

    def __post_init__(self) -> None:
        constant_speed_q(self.constant_speed_psd)
        check_track_psd("--track-psd", self.track_psd)
        check_one_of(self.planner_distance, DISTANCE_POINTS, "--planner-distance")
        check_one_of(self.preset, PRESETS, "--config")
        check_one_of(self.noise_split, NOISE_SPLITS, "--noise-split")
        check_one_of(self.method, DEPLOY_METHODS, "--method")
        check_one_of(self.label_drones, LABEL_DRONES, "--label-drones")
        for name in ("duration", "fl_period", "deadline_ms", "start_timeout", "round_timeout"):
            if not getattr(self, name) > 0:
                raise ValueError(f"--{name.replace('_', '-')}: must be positive")

    @property
    def link(self) -> LinkConfig:
        tls = CertificateFolder(Path(self.tls_dir)).zenoh("cloud") if self.tls_dir else None
        return LinkConfig((self.listen,), (self.connect,), tls)

    def to_run_config(self) -> dict[str, str | float | bool]:
        """The settings as the ServerApp's run config. TOML has no null and Flower takes only
        the keys the app declares (``pyproject.toml``), so an optional number that is
        ``None`` travels as 0 (never a valid value of one: each must be positive)."""
        return {
            _PREFIX + k.replace("_", "-"): 0.0 if v is None else v for k, v in asdict(self).items()
        }

    @classmethod
    def from_run_config(cls, config: dict) -> CloudSettings:
        """Parse the ServerApp's run config (TOML: a flag arrives as a bool). A flag that is
        not a bool (``"false"`` would be true to ``bool``) raises :class:`CloudError` naming
        the key, as :meth:`FlSettings.from_run_config` does."""
        values = {}
        for name, kind in cls.__annotations__.items():
            key = _PREFIX + name.replace("_", "-")
            if key not in config:
                continue
            value = config[key]
            if kind == "bool" and not isinstance(value, bool):
                raise CloudError(f"run config: {key!r} must be a bool, got {value!r}")
            if kind == "float | None":
                value = float(value) or None  # 0 stands for None (to_run_config)
            elif kind == "float":
                value = float(value)
            elif kind != "bool":
                value = str(value)
            values[name] = value
        return cls(**values)


app = ServerApp()


@app.main()
def main(grid: Grid, context: Context) -> None:
    torch.set_num_threads(1)
    run_config = dict(context.run_config)
    CloudEpisode(
        grid, CloudSettings.from_run_config(run_config), FlSettings.from_run_config(run_config)
    ).run()


@dataclass
class _Inbox:
    """What arrived from the world and the drones, by step (filled on Zenoh threads)."""

    telemetry: dict[int, TelemetryMessage] = field(default_factory=dict)
    predictions: dict[int, dict[int, PredictionMessage]] = field(default_factory=dict)
    reports: dict[int, dict[int, NoiseReportMessage]] = field(default_factory=dict)
    late: dict[int, int] = field(default_factory=dict)  # drone -> predictions after deadline
    changed: threading.Condition = field(default_factory=threading.Condition)


class CloudEpisode:
    """One episode's cloud side (see the module docstring)."""

    def __init__(self, grid: Grid, settings: CloudSettings, fl: FlSettings) -> None:
        self.grid = grid
        self.settings = settings
        self.fl = fl
        self.scenario: Scenario = load_scenario(settings.scenario)
        s = self.scenario
        self.n_steps = int(round(settings.duration * s.rate_hz))
        self.fl_every = int(round(settings.fl_period * s.rate_hz))
        fusion = replace(
            fusion_config(s, constant_speed_psd=settings.constant_speed_psd),
            noise_split=settings.noise_split,
            coverage_noise=COVERAGE_NOISE_PROFILE if settings.coverage_noise else None,
            temporal_kernel=TEMPORAL_KERNEL if settings.temporal_kernel else None,
        )
        # The planner's tracks; with a q of their own the labels have a filter of their own.
        self.fusion = fusion
        self.label_fuser: Fuser | None = None
        if settings.track_psd is not None:
            self.label_fuser = Fuser(s.target_ids, s.drone_ids, fusion)
        self.fuser = Fuser(
            s.target_ids, s.drone_ids, planner_filter_config(fusion, settings.track_psd)
        )
        self.planner = DroneFLPlanner.from_scenario(
            s, PlannerConfig(distance_at=settings.planner_distance)
        )
        self.counter = ByteCounter()
        self.inbox = _Inbox()
        saved = load_model(Path(settings.model))
        if saved.model != fl.model:
            raise CloudError(
                f"{settings.model}: its model is not the one --config {settings.preset} trains"
            )
        self.state = saved.state
        self.history: list[RoundRecord] = []
        self.control: dict[str, torch.Tensor] | None = None  # SCAFFOLD's c, kept across rounds
        self.rounds: list[DeployedRound] = []
        self.nodes: dict[int, int] = {}  # drone id -> its SuperNode's id
        m, n = len(s.drones), len(s.targets)
        self.prediction = np.full((self.n_steps, m, n, 2), np.nan)
        self.noise = np.full((self.n_steps, m, n, 2, 2), np.nan)  # the reports received, m^2
        self.drone_position = np.full((self.n_steps, m, 2), np.nan)  # telemetry of each step
        self.track_position = np.full((self.n_steps + 1, n, 2), np.nan)
        self.trace = np.full((self.n_steps, n), np.nan)
        self.cost = np.zeros(self.n_steps)
        self.silent = np.zeros((self.n_steps, m), dtype=bool)
        self.step_ms = np.full(self.n_steps, np.nan)  # telemetry in -> controls out, wall ms
        self.telemetry_bytes = 0
        self.fl_steps: list[int] = []
        self.planner_seconds = 0.0
        self.current = 0
        self.column = {t: j for j, t in enumerate(s.target_ids)}

    # -- Zenoh callbacks -------------------------------------------------------------------

    def _on_telemetry(self, _: str, payload: bytes) -> None:
        message = TelemetryMessage.decode(payload)
        with self.inbox.changed:
            self.telemetry_bytes += len(payload)
            self.inbox.telemetry[message.step] = message
            self.inbox.changed.notify_all()

    def _on_prediction(self, key: str, payload: bytes) -> None:
        drone_id = int(key.split("/")[2])
        predictions, report = split_uplink(payload)
        try:
            message = PredictionMessage.decode(predictions)
            noise = NoiseReportMessage.decode(report) if report else None
        except WireError as exc:
            log(WARNING, "drone %d: undecodable prediction message (%s)", drone_id, exc)
            return
        with self.inbox.changed:
            self.counter.add(drone_id, "up", "predictions", len(predictions))
            if report:
                self.counter.add(drone_id, "up", "noise_reports", len(report))
            if message.drone_id != drone_id or message.step < self.current:
                self.inbox.late[drone_id] = self.inbox.late.get(drone_id, 0) + 1
                return
            self.inbox.predictions.setdefault(message.step, {})[drone_id] = message
            if noise is not None:
                self.inbox.reports.setdefault(message.step, {})[drone_id] = noise
            self.inbox.changed.notify_all()

    # -- the episode -----------------------------------------------------------------------

    def run(self) -> None:
        s = self.settings
        with Link(s.link) as link:
            self.link = link
            link.watch_alive()
            link.subscribe(TELEMETRY, self._on_telemetry)
            link.subscribe(PREDICTIONS.format(id="*"), self._on_prediction)
            log(INFO, "cloud: waiting for the world, the drones and their SuperNodes")
            self._wait_for_peers()
            link.announce("cloud")
            log(INFO, "cloud: all peers up, episode of %d steps starts", self.n_steps)
            wall = time.perf_counter()
            for k in range(self.n_steps):
                self._step(k)
            wall = time.perf_counter() - wall
        self._save(wall)
        log(INFO, "cloud: episode done in %.1f s wall, %d FL rounds", wall, len(self.rounds))

    def _wait_for_peers(self) -> None:
        s, drones = self.settings, self.scenario.drone_ids
        missing = self.link.wait_alive({"world", *(f"drone/{d}" for d in drones)}, s.start_timeout)
        if missing:
            raise CloudError(
                f"no answer from {', '.join(sorted(missing))} within {s.start_timeout:.0f} s"
            )
        if self.settings.method != "dronefl":
            return
        deadline = time.monotonic() + s.start_timeout
        while (absent := self._refresh_nodes(drones)) and time.monotonic() < deadline:
            time.sleep(0.5)
        if absent:
            raise CloudError(
                f"SuperNodes of drones {absent} did not connect to the SuperLink within "
                f"{s.start_timeout:.0f} s"
            )

    def _refresh_nodes(self, drones: list[int] | tuple[int, ...]) -> list[int]:
        """Ask each of ``drones`` for its SuperNode's id (a restarted drone has a new one);
        returns the drones whose SuperNode is not connected to the SuperLink."""
        connected = set(self.grid.get_node_ids())
        absent = []
        for drone_id in drones:
            answer = self.link.request(NODE.format(id=drone_id), timeout=5.0)
            node = int(answer) if answer else None
            if node is None or node not in connected:
                absent.append(drone_id)
                continue
            if self.nodes.get(drone_id) != node:
                log(INFO, "cloud: drone %d has SuperNode %d", drone_id, node)
            self.nodes[drone_id] = node
        return absent

    def _alive_drones(self) -> list[int]:
        alive = self.link.alive()
        return [d for d in self.scenario.drone_ids if f"drone/{d}" in alive]

    def _wait_telemetry(self, k: int) -> TelemetryMessage:
        stall = self.settings.start_timeout
        with self.inbox.changed:
            deadline = time.monotonic() + stall
            while k not in self.inbox.telemetry:
                if "world" not in self.link.alive():
                    raise CloudError(f"the world left before step {k}")
                if time.monotonic() > deadline:
                    raise CloudError(f"no telemetry of step {k} within {stall:.0f} s")
                self.inbox.changed.wait(0.2)
            return self.inbox.telemetry.pop(k)

    def _wait_predictions(
        self, k: int
    ) -> tuple[dict[int, PredictionMessage], dict[int, NoiseReportMessage]]:
        """Step ``k``'s prediction messages and noise reports by drone, as they arrived by the
        deadline."""
        expected = set(self._alive_drones())
        deadline = time.perf_counter() + self.settings.deadline_ms / 1000
        with self.inbox.changed:
            while not expected <= set(self.inbox.predictions.get(k, {})):
                left = deadline - time.perf_counter()
                if left <= 0:
                    break
                self.inbox.changed.wait(left)
            self.current = k + 1  # anything for step k from now on is late
            return self.inbox.predictions.pop(k, {}), self.inbox.reports.pop(k, {})

    def _step(self, k: int) -> None:
        telemetry = self._wait_telemetry(k)
        started = time.perf_counter()
        row = {d.drone_id: d.position for d in telemetry.drones}
        for i, drone_id in enumerate(self.scenario.drone_ids):
            self.drone_position[k, i] = row.get(drone_id, (np.nan, np.nan))
        received, reports = self._wait_predictions(k)
        measurements = []
        for i, drone_id in enumerate(self.scenario.drone_ids):
            message = received.get(drone_id)
            if message is None:
                self.silent[k, i] = True
                continue
            report = reports.get(drone_id)
            noise = dict(zip(report.target_ids, report.noise, strict=True)) if report else {}
            for target_id, position in zip(
                message.target_ids, message.positions[:, 0], strict=True
            ):
                if target_id not in self.column:
                    continue
                self.prediction[k, i, self.column[target_id]] = position
                if target_id in noise:
                    self.noise[k, i, self.column[target_id]] = noise[target_id]
                measurements.append(
                    PositionMeasurement(drone_id, target_id, position, noise.get(target_id))
                )
        dt = self.scenario.dt
        tracks, fused = update_filters(self.fuser, self.label_fuser, telemetry.t + dt, measurements)
        for target_id, track in tracks.items():
            self.track_position[k + 1, self.column[target_id]] = track.position
        for target_id, track in fused.items():  # the uncertainty the planner trades
            self.trace[k, self.column[target_id]] = np.trace(track.covariance)
        t0 = time.perf_counter()
        forecast = planner_forecast(self.fuser, self.label_fuser, tracks, dt)
        plan = self.planner.plan(telemetry.drones, forecast)
        self.planner_seconds += time.perf_counter() - t0
        self.cost[k] = plan.cost.total
        for drone_id in self.scenario.drone_ids:
            ax, ay = plan.accelerations[drone_id]
            data = ControlMessage(drone_id, k, (float(ax), float(ay))).encode()
            self.counter.add(
                drone_id, "down", "control", self.link.put(CONTROL.format(id=drone_id), data)
            )
        self.step_ms[k] = 1000 * (time.perf_counter() - started)
        if (
            self.settings.method == "dronefl"
            and (k + 1) % self.fl_every == 0
            and k + 1 < self.n_steps
        ):
            self._play_round(k + 1)
        self.link.put(RELEASE, encode_release(k))
        if (k + 1) % 100 == 0:
            log(INFO, "cloud: step %d/%d", k + 1, self.n_steps)

    # -- FL rounds -------------------------------------------------------------------------

    def _play_round(self, steps: int) -> None:
        """One FL round on the data of steps ``0 .. steps-1`` (the world waits meanwhile)."""
        started = time.perf_counter()
        server_round = len(self.rounds) + 1
        # The same labels as `dronefl track`'s default: the fused tracks, RTS-smoothed, each
        # drone's kept by the --label-drones rule and de-shrunk with --deshrink-labels.
        t = np.arange(steps) * self.scenario.dt
        labelled = self.fuser if self.label_fuser is None else self.label_fuser
        smoothed = make_labels("smoothed", labelled, t).position
        altitudes = [d.altitude for d in self.scenario.drones]
        own, pull = training_labels(
            smoothed, self.prediction, self.drone_position[:steps], altitudes,
            self.settings.label_drones, self.settings.deshrink_labels,
            self.scenario.assignment() if self.settings.detected_only else None,
        )  # fmt: skip
        if self.settings.deshrink_labels:
            log(INFO, "round %d: labels de-shrunk by the pull %.3f", server_round, pull)
        per_drone = dict(zip(self.scenario.drone_ids, own, strict=True))
        if not np.isfinite(own).any():
            log(INFO, "round %d: no drone has a label (--label-drones); none played", server_round)
            return
        ready = []
        for drone_id in self._alive_drones():
            labels = LabelsMessage(server_round, self.scenario.target_ids, per_drone[drone_id])
            payload = labels.encode()
            answer = self.link.request(FLUSH.format(id=drone_id), payload, timeout=30.0)
            if answer == b"ok":
                ready.append(drone_id)
                self.counter.add(drone_id, "down", "labels", len(payload))
        absent = self._refresh_nodes(ready)
        # A drone that came back (restarted) is live before its new SuperNode has reached the
        # SuperLink (which polls every few seconds): wait a little for it rather than leave it out.
        deadline = time.monotonic() + SUPERNODE_JOIN_S
        while absent and time.monotonic() < deadline:
            time.sleep(1.0)
            absent = self._refresh_nodes(ready)
        nodes = {self.nodes[d]: d for d in ready if d not in absent}  # node id -> drone
        trained: dict[int, float] = {}
        rejected: tuple[str, ...] = ()
        weights: dict[str, dict[int, int]] = {"down": {}, "up": {}}
        if nodes:
            grid = DroneGrid(self.grid, nodes, self._is_alive, self.settings.round_timeout)
            driver = RoundDriver(grid, self.fl, len(nodes), self.history, self.control)
            new_state = driver.play(self.state, server_round)
            if driver.history and driver.history[-1].server_round == server_round:
                self.history = driver.history
                result = driver.history[-1]
                trained = dict(result.train_loss)
                rejected = result.rejected
                if trained:
                    self.state, self.control = new_state, driver.control
                    traffic = {"down": dict(result.bytes_down), "up": dict(result.bytes_up)}
                    weights = self._install(grid, server_round, nodes, set(trained), traffic)
        participants = tuple(sorted(trained))
        entry = DeployedRound(
            round=server_round,
            t=steps * self.scenario.dt,
            seconds=time.perf_counter() - started,
            train_loss=trained,
            rejected=rejected,
            weight_bytes_down=weights["down"],
            weight_bytes_up=weights["up"],
            pull=pull,
            step=steps,
            participants=participants,
            missing=tuple(d for d in self.scenario.drone_ids if d not in participants),
        )
        if entry.missing:
            log(WARNING, "round %d: no update from drones %s", server_round, list(entry.missing))
        self.rounds.append(entry)
        self.fl_steps.append(steps)
        log(INFO, "cloud: round %d done in %.1f s", server_round, entry.seconds)

    def _is_alive(self, drone_id: int) -> bool:
        return f"drone/{drone_id}" in self.link.alive()

    def _install(
        self,
        grid: DroneGrid,
        server_round: int,
        nodes: dict[int, int],
        trained: set[int],
        traffic: dict,
    ) -> dict[str, dict[int, int]]:
        """Send the new global model to the nodes of the round whose drone trained in it and
        have the drone load it (a drone that sat the round out keeps the model it flies, as in
        ``dronefl track``); returns (and counts) the round's weight bytes per drone, by
        direction."""
        weights: dict[str, dict[int, int]] = {"down": {}, "up": {}}
        for direction in DIRECTIONS:  # the round's training messages, shared evenly
            share = traffic.get(direction, {}).get("train", 0) // len(nodes)
            for drone in nodes.values():
                weights[direction][drone] = share
        content = RecordDict(
            {
                ARRAYS_KEY: self.fl.layout.pack(self.state),
                "config": ConfigRecord({ROUND_KEY: server_round}),
            }
        )
        messages = [
            Message(content, node, "query", group_id=f"install-{server_round}")
            for node, drone in nodes.items()
            if drone in trained
        ]
        for message in messages:
            drone = nodes[message.metadata.dst_node_id]
            weights["down"][drone] += message_bytes(message)
        for direction, per_drone in weights.items():
            for drone, n_bytes in per_drone.items():
                self.counter.add(drone, direction, "weights", n_bytes)
        for reply in grid.send_and_receive(messages):
            drone = nodes.get(reply.metadata.src_node_id)
            if drone is None or reply.has_error():
                continue
            answer = self.link.request(RELOAD.format(id=drone), str(server_round).encode(), 30.0)
            if answer != b"ok":
                log(WARNING, "round %d: drone %d did not load the new model", server_round, drone)
        return weights

    # -- results ---------------------------------------------------------------------------

    def _save(self, wall: float) -> None:
        out = Path(self.settings.out)
        atomic_savez(
            out / "cloud.npz",
            prediction=self.prediction,
            noise=self.noise,
            track_position=self.track_position,
            trace=self.trace,
            cost=self.cost,
            silent=self.silent,
            step_ms=self.step_ms,
            fl_steps=np.array(self.fl_steps, dtype=np.int64),
        )
        traffic = tuple(
            TrafficCount(d, way, kind, n)
            for d in self.scenario.drone_ids
            for way in DIRECTIONS
            for kind in ("predictions", "noise_reports", "control", "labels", "weights")
            if (n := self.counter.total(d, way, kind))
        )
        CloudLog(
            wall_seconds=wall,
            planner_ms_per_step=1000 * self.planner_seconds / self.n_steps,
            gating_rejections=int(self.fuser.rejections),
            track_resets=int(self.fuser.resets),
            rounds=tuple(self.rounds),
            late_predictions=dict(sorted(self.inbox.late.items())),
            traffic=traffic,
            telemetry_bytes=self.telemetry_bytes,
            supernodes=dict(sorted(self.nodes.items())),
            settings=asdict(self.settings),
            fusion_config=fusion_record(self.fusion),
        ).save(out / "cloud.json")
