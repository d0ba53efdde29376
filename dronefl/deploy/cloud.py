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
from dataclasses import asdict, dataclass, field
from logging import INFO, WARNING
from pathlib import Path

import numpy as np
import torch
from flwr.app import ConfigRecord, Context, Message, RecordDict
from flwr.common.logger import log
from flwr.serverapp import Grid, ServerApp

from dronefl.accounting import DIRECTIONS, ByteCounter
from dronefl.config import Scenario, load_scenario
from dronefl.deploy import CloudError, check_deploy_method
from dronefl.deploy.certs import CertificateFolder
from dronefl.deploy.clientapp import load_model
from dronefl.deploy.grid import DroneGrid
from dronefl.deploy.link import (
    CLOUD,
    CONTROL,
    FLUSH,
    NODE,
    PREDICTIONS,
    RELEASE,
    RELOAD,
    TELEMETRY,
    Link,
    LinkConfig,
    check_endpoint,
)
from dronefl.deploy.messages import LabelsMessage, TelemetryMessage, encode_release
from dronefl.deploy.results import CloudLog, DeployedRound, TrafficCount
from dronefl.fl.records import ARRAYS_KEY, ROUND_KEY, FlSettings, RoundRecord
from dronefl.fl.server_app import RoundDriver
from dronefl.fl.traffic import message_bytes
from dronefl.io import atomic_savez
from dronefl.learners import LEARNERS
from dronefl.roles import CloudNode, Received
from dronefl.settings import Setting, SettingError
from dronefl.validation import check_positive
from dronefl.wire import (
    ControlMessage,
    NoiseReportMessage,
    PredictionMessage,
    WireError,
    split_uplink,
)

#: How long a round waits for a live drone's SuperNode to join, s: a restarted drone flies
#: before its new SuperNode has joined, and with SuperNode authentication the SuperLink admits
#: that SuperNode only once the killed one's key is free again, up to 2 missed heartbeats of
#: 30 s after the kill (Flower 1.41), then at the drone's next retry (every 8 s at most).
SUPERNODE_JOIN_S = 75.0

_PREFIX = "deploy-"


@dataclass(frozen=True)
class CloudSettings:
    """The cloud's side of one deployed episode (passed as the ServerApp's run config).

    ``scenario`` flown for ``duration`` s by ``method`` (a :data:`~dronefl.learners.LEARNERS`
    method a deployment runs, :func:`~dronefl.deploy.check_deploy_method`) as ``setting``
    says (the resolved setting as TOML text, :meth:`~dronefl.settings.Setting.to_toml`: the
    processes receive it whole); ``model`` the pretrained weights (a file written by
    :func:`~dronefl.deploy.clientapp.save_model`); ``out`` where ``cloud.npz`` /
    ``cloud.json`` go; ``deadline_ms`` wall ms the cloud waits for a step's predictions;
    ``listen`` / ``connect`` its Zenoh endpoints; ``tls_dir`` the certificate folder (empty:
    plain TCP, no authentication); ``start_timeout`` s for the world, the drones and their
    SuperNodes to appear; ``round_timeout`` s for one FL message exchange.
    """

    scenario: str
    model: str
    out: str
    setting: str
    method: str
    duration: float
    deadline_ms: float
    listen: str
    connect: str
    tls_dir: str
    start_timeout: float
    round_timeout: float = 300.0

    def __post_init__(self) -> None:
        check_deploy_method(self.method)
        try:
            Setting.from_toml(self.setting, "deployed")
        except SettingError as exc:
            raise CloudError(f"run config: {exc}") from None
        for name in ("duration", "deadline_ms", "start_timeout", "round_timeout"):
            check_positive(getattr(self, name), f"--{name.replace('_', '-')}")
        check_endpoint(self.listen, "--listen")
        check_endpoint(self.connect, "--connect")

    @property
    def resolved(self) -> Setting:
        """The episode's setting."""
        return Setting.from_toml(self.setting, "deployed")

    def link(self, drone_ids: tuple[int, ...]) -> LinkConfig:
        """The cloud's link in a deployment flying ``drone_ids``."""
        tls = CertificateFolder(Path(self.tls_dir)).zenoh(CLOUD) if self.tls_dir else None
        return LinkConfig((self.listen,), (self.connect,), tls, drone_ids)

    def to_run_config(self) -> dict[str, str | float]:
        """The settings as the ServerApp's run config (``pyproject.toml`` declares each key)."""
        return {_PREFIX + k.replace("_", "-"): v for k, v in asdict(self).items()}

    @classmethod
    def from_run_config(cls, config: dict) -> CloudSettings:
        """Parse the ServerApp's run config; :class:`CloudError` naming a missing key."""
        values = {}
        for name, kind in cls.__annotations__.items():
            key = _PREFIX + name.replace("_", "-")
            if key not in config:
                continue
            values[name] = float(config[key]) if kind == "float" else str(config[key])
        try:
            return cls(**values)
        except TypeError as exc:
            raise CloudError(f"run config: {exc}") from None


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
    """One episode's cloud side (see the module docstring): a
    :class:`~dronefl.roles.CloudNode` fed by what arrives over Zenoh."""

    def __init__(self, grid: Grid, settings: CloudSettings, fl: FlSettings) -> None:
        self.grid = grid
        self.settings = settings
        self.fl = fl
        self.scenario: Scenario = load_scenario(settings.scenario)
        self.setting = settings.resolved
        s = self.scenario
        self.n_steps = int(round(settings.duration * s.rate_hz))
        self.fl_every = int(round(self.setting.learning.period * s.rate_hz))
        self.federated = LEARNERS[settings.method].federated
        self.node = CloudNode(s, self.setting)
        self.counter = ByteCounter()
        self.inbox = _Inbox()
        saved = load_model(Path(settings.model))
        if saved.model != fl.model:
            raise CloudError(f"{settings.model}: its model is not the one the setting trains")
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
        with Link(s.link(self.scenario.drone_ids)) as link:
            self.link = link
            link.watch_alive()
            link.subscribe(TELEMETRY, self._on_telemetry)
            for d in self.scenario.drone_ids:  # one key per drone: each may put on its own only
                link.subscribe(PREDICTIONS.format(id=d), self._on_prediction)
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
        if not self.federated:
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
        messages, reports = self._wait_predictions(k)
        received = []
        for i, drone_id in enumerate(self.scenario.drone_ids):
            message = messages.get(drone_id)
            if message is None:
                self.silent[k, i] = True
                continue
            report = reports.get(drone_id)
            noise = dict(zip(report.target_ids, report.noise, strict=True)) if report else {}
            positions = message.positions[:, 0]
            for target_id, position in zip(message.target_ids, positions, strict=True):
                if target_id not in self.column:
                    continue
                self.prediction[k, i, self.column[target_id]] = position
                if target_id in noise:
                    self.noise[k, i, self.column[target_id]] = noise[target_id]
            received.append(Received(drone_id, message.target_ids, positions, noise))
        fused = self.node.fuse(telemetry.t + self.scenario.dt, received)
        for target_id, track in fused.tracks.items():
            self.track_position[k + 1, self.column[target_id]] = track.position
        for target_id, track in fused.fused.items():  # the uncertainty the planner trades
            self.trace[k, self.column[target_id]] = np.trace(track.covariance)
        plan = self.node.plan(telemetry.drones, fused)
        self.cost[k] = plan.cost.total
        for drone_id in self.scenario.drone_ids:
            ax, ay = plan.accelerations[drone_id]
            data = ControlMessage(drone_id, k, (float(ax), float(ay))).encode()
            self.counter.add(
                drone_id, "down", "control", self.link.put(CONTROL.format(id=drone_id), data)
            )
        self.step_ms[k] = 1000 * (time.perf_counter() - started)
        if self.federated and (k + 1) % self.fl_every == 0 and k + 1 < self.n_steps:
            self._play_round(k + 1)
        self.link.put(RELEASE, encode_release(k))
        if (k + 1) % 100 == 0:
            log(INFO, "cloud: step %d/%d", k + 1, self.n_steps)

    # -- FL rounds -------------------------------------------------------------------------

    def _play_round(self, steps: int) -> None:
        """One FL round on the data of steps ``0 .. steps-1`` (the world waits meanwhile)."""
        started = time.perf_counter()
        server_round = len(self.rounds) + 1
        # The labels `dronefl track` gives: the cloud node's, from what the cloud received.
        own = self.node.labels(np.arange(steps) * self.scenario.dt, self.prediction)
        per_drone = dict(zip(self.scenario.drone_ids, own, strict=True))
        if not np.isfinite(own).any():
            log(INFO, "round %d: no drone has a label (learning.label_drones)", server_round)
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
        # A drone that came back (restarted) is live before its new SuperNode has joined the
        # SuperLink: wait for it (SUPERNODE_JOIN_S) rather than leave it out.
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
            planner_ms_per_step=1000 * self.node.planner_seconds / self.n_steps,
            gating_rejections=self.node.rejections,
            track_resets=self.node.resets,
            rounds=tuple(self.rounds),
            late_predictions=dict(sorted(self.inbox.late.items())),
            traffic=traffic,
            telemetry_bytes=self.telemetry_bytes,
            supernodes=dict(sorted(self.nodes.items())),
            settings={k: v for k, v in asdict(self.settings).items() if k != "setting"},
            setting_name=self.setting.name,
            setting=self.setting.to_dict(),
        ).save(out / "cloud.json")
