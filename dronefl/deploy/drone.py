"""A drone process (``dronefl drone --id I``): the onboard side of one drone.

Each step it receives its sensors from the world (odometry and detections), appends them to
its onboard record, predicts its assigned targets' next positions with the trajectory
transformer on ONNX Runtime and publishes them to the cloud
(:class:`~dronefl.wire.PredictionMessage`; an empty one when it has nothing to predict yet,
so that the cloud need not wait for it); the cloud's control
(:class:`~dronefl.wire.ControlMessage`) it hands on to its autopilot (the world).

Beside it runs its Flower SuperNode (``flower-supernode``, a child process), whose node
config names the drone and its data folder; the drone flies while the SuperNode joins the
SuperLink (:class:`SuperNodeJoin`) and tells the cloud (Zenoh query ``node``) which node id
the SuperLink gave it, so that a round is sent to the SuperNodes of the live drones only.
Before an FL round the cloud asks the drone (Zenoh query ``flush``) to write its onboard
record and the round's pseudo-labels there; after the round the ClientApp has written the
new global model there, and the cloud asks the drone (``reload``) to load it into its
predictor.

The drone ends when the world does (its liveliness goes), writing its record a last time.
"""

from __future__ import annotations

import json
import queue
import re
import shlex
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from dronefl.config import load_scenario
from dronefl.deploy.certs import CertificateFolder
from dronefl.deploy.clientapp import GLOBAL_MODEL, load_model
from dronefl.deploy.flower import flower_env, supernode_command
from dronefl.deploy.link import (
    ACTUATE,
    CONTROL,
    EPISODE,
    FLUSH,
    NODE,
    PREDICTIONS,
    RELOAD,
    SENSE,
    Link,
    LinkConfig,
    check_endpoint,
    drone_role,
)
from dronefl.deploy.messages import LabelsMessage, SenseMessage
from dronefl.deploy.processes import Child, Children, DeployError, port_open, wait_for
from dronefl.logs import PseudoLabels
from dronefl.models.model import build_model
from dronefl.models.online import OnboardRecord
from dronefl.models.predictor import TrajectoryPredictor
from dronefl.roles import DroneNode
from dronefl.settings import Setting

#: How the SuperNode logs the node id the SuperLink assigned it.
_NODE_ID = re.compile(r"SuperNode ID: (\d+)")


@dataclass(frozen=True)
class DroneSettings:
    """One drone process.

    ``scenario`` and ``drone_id`` which drone it is; ``model`` the pretrained weights;
    ``data_dir`` the drone's disk; ``setting`` the episode's (what the drone sends is its
    ``[drone]`` sub-config, :class:`~dronefl.roles.DroneNode`); ``connect`` the Zenoh
    endpoints of the world and the cloud (``host:port``); ``superlink`` the SuperLink's
    ``host:port``; ``runtime_port`` the port of this SuperNode's local ClientApp API;
    ``tls_dir`` the certificate folder (empty: plain TCP and no authentication; else also
    SuperNode authentication with this drone's key); ``start_timeout`` s to wait for the
    world and the SuperLink.
    """

    scenario: str
    drone_id: int
    model: Path
    data_dir: Path
    setting: Setting
    connect: tuple[str, ...]
    superlink: str
    runtime_port: int
    tls_dir: str = ""
    start_timeout: float = 120.0

    def __post_init__(self) -> None:
        if not self.connect:
            raise ValueError("--connect: give the world's and the cloud's host:port")
        for endpoint in self.connect:
            check_endpoint(endpoint, "--connect")
        check_endpoint(self.superlink, "--superlink")
        if not 1 <= self.runtime_port <= 65535:
            raise ValueError(f"--runtime-port: {self.runtime_port} is not a port (1-65535)")

    @property
    def link(self) -> LinkConfig:
        certs = CertificateFolder(Path(self.tls_dir)) if self.tls_dir else None
        tls = certs.zenoh(drone_role(self.drone_id)) if certs else None
        return LinkConfig((), self.connect, tls, (self.drone_id,))


class DroneProcess:
    """The drone's :class:`~dronefl.roles.DroneNode` between Zenoh callbacks and its main
    loop."""

    def __init__(self, settings: DroneSettings, info: dict, predictor: TrajectoryPredictor) -> None:
        scenario = load_scenario(settings.scenario)
        spec = scenario.drone(settings.drone_id)
        self.settings = settings
        self.dt = float(info["dt"])
        meta = {k: info[k] for k in ("scenario", "environment", "seed")}
        setting = settings.setting
        self.node = DroneNode(
            spec, scenario, setting.drone, setting.model.past_steps, int(info["steps"]), meta,
            predictor,
        )  # fmt: skip
        self.predictor = predictor
        self.lock = threading.Lock()  # the node
        self.sensed: queue.Queue[bytes] = queue.Queue()
        self.log_path = Path(settings.data_dir) / f"drone_{spec.id}.npz"

    @property
    def record(self) -> OnboardRecord:
        """The drone's onboard record."""
        return self.node.record

    def flush(self, payload: bytes) -> bytes:
        """Write the onboard record and the round's pseudo-labels on their steps to disk."""
        labels = LabelsMessage.decode(payload)
        with self.lock:
            if self.record.steps <= self.node.past_steps:
                return b"too little data"
            log = self.record.to_log()
            log.save(self.log_path)
        rows = np.rint(log.t / self.dt).astype(int)
        if rows.max() >= len(labels.position):
            return b"labels do not cover the record"
        target_ids = np.array(labels.target_ids, dtype=np.int32)
        PseudoLabels(log.t, target_ids, labels.position[rows]).save(
            Path(self.settings.data_dir) / "tracks.npz"
        )
        return b"ok"

    def reload(self, payload: bytes) -> bytes:
        """Load the global model the ClientApp wrote to disk for the round in ``payload``."""
        saved = load_model(Path(self.settings.data_dir) / GLOBAL_MODEL)
        if saved.server_round != int(payload.decode()):
            return f"model on disk is of round {saved.server_round}".encode()
        if saved.model != self.predictor.config:
            return b"model on disk is of another architecture than the one flown"
        with self.lock:
            self.predictor.load_state(saved.state)
            self.node.install(self.predictor)
        print(
            f"drone {self.settings.drone_id}: model of round {saved.server_round} loaded",
            flush=True,
        )
        return b"ok"

    def predict(self, payload: bytes) -> bytes:
        """Record one step's sensors and return what the drone sends
        (:meth:`~dronefl.roles.DroneNode.uplink`'s payload: the prediction message, followed
        by the noise report when the drone reports, :func:`~dronefl.wire.split_uplink`)."""
        sense = SenseMessage.decode(payload)
        with self.lock:
            self.node.sense(sense.odometry, sense.detections)
            return self.node.uplink(sense.step, self.node.forecast()).payload


def load_predictor(path: Path, past_steps: int) -> TrajectoryPredictor:
    """The predictor the model file ``path`` holds (its architecture and weights), on ONNX
    Runtime; ``past_steps`` L_p is what the drone's record feeds it."""
    saved = load_model(path)
    if saved.model.past_steps != past_steps or saved.model.future_steps != 1:
        raise DeployError(
            f"--model: {path} holds a model of L_p = {saved.model.past_steps}, L_f = "
            f"{saved.model.future_steps}; the drone feeds L_p = {past_steps} and flies L_f = 1"
        )
    model = build_model(saved.model)
    try:
        model.load_state_dict(saved.state)
    except RuntimeError:
        raise DeployError(
            f"--model: {path} does not hold the DroneFL predictor's weights"
        ) from None
    return TrajectoryPredictor(model, runtime="onnx")


def run_drone(settings: DroneSettings, logs: Path) -> None:
    """Run the drone until the world's episode ends."""
    scenario = load_scenario(settings.scenario)
    if settings.drone_id not in scenario.drone_ids:
        raise DeployError(
            f"--id: drone {settings.drone_id} is not in scenario {scenario.name} "
            f"(drones {', '.join(map(str, scenario.drone_ids))})"
        )
    torch.set_num_threads(1)
    predictor = load_predictor(Path(settings.model), settings.setting.model.past_steps)
    Path(settings.data_dir).mkdir(parents=True, exist_ok=True)
    host, port = settings.superlink.rsplit(":", 1)
    with Children(logs) as children, Link(settings.link) as link:
        wait_for(
            lambda: port_open(host, int(port)),
            settings.start_timeout,
            f"the SuperLink at {settings.superlink} (unreachable)",
        )
        supernode = SuperNodeJoin(settings, children)
        info = _episode(link, settings, supernode)
        drone = DroneProcess(settings, info, predictor)
        _serve(link, drone, supernode)
        link.watch_alive()
        if link.wait_alive({"world"}, settings.start_timeout):
            raise DeployError(f"the world did not appear within {settings.start_timeout:.0f} s")
        link.announce(f"drone/{settings.drone_id}")
        print(f"drone {settings.drone_id}: up, {info['steps']} steps", flush=True)
        _loop(link, drone, supernode)


class SuperNodeJoin:
    """The drone's SuperNode, joining the SuperLink while the drone flies: each call of
    :meth:`tend` moves the join on without waiting.

    The SuperNode has joined once the SuperLink has admitted it (it logs its node id). One
    that exits first is started again after 1, 2, 4, 8, 8, ... s while that still falls within
    ``start_timeout``; then the SuperLink's refusal is the error. Refusals are expected for a
    while: before the cloud has registered the drone's key, and, with SuperNode
    authentication, after a restart, until the SuperLink lets go of the killed SuperNode's
    key (two missed 30 s heartbeats, Flower 1.41). The drone flies meanwhile, and the cloud
    leaves it out of the rounds until it has joined."""

    def __init__(self, settings: DroneSettings, children: Children) -> None:
        certs = CertificateFolder(Path(settings.tls_dir)) if settings.tls_dir else None
        self.command = supernode_command(
            settings.drone_id, settings.data_dir, settings.superlink, settings.runtime_port,
            settings.start_timeout, certs,
        )  # fmt: skip
        self.env = flower_env(Path(settings.data_dir) / "flwr")
        self.settings = settings
        self.children = children
        self.deadline = time.monotonic() + settings.start_timeout
        self.refused: str | None = None  # why the SuperLink turned the attempts away
        self.pause = 1.0  # s before the next attempt, doubled up to 8 s
        self.retry_at: float | None = None  # when the next attempt starts
        self.node = b""  # the node id the SuperLink gave it, once admitted
        print(f"drone {settings.drone_id}: {shlex.join(self.command)}", flush=True)
        self.child = self._start()

    def _start(self) -> Child:
        return self.children.start(f"supernode-{self.settings.drone_id}", self.command, self.env)

    def tend(self) -> None:
        """Note the node id once the SuperNode has one, start a refused SuperNode again when
        its pause is over; :class:`DeployError` when the join failed or a joined SuperNode
        exited."""
        now = time.monotonic()
        if self.node:
            if self.child.process.poll() is not None:
                raise DeployError(
                    f"the SuperNode exited with code {self.child.process.returncode}: "
                    f"{self.child.last_line()}"
                )
            return
        if self.child.process.poll() is None:
            self.node = supernode_id(self.child)
        elif self.retry_at is None:  # it has just exited: refused
            self.refused = _refusal(self.child.output(), self.refused)
            self.retry_at = now + self.pause
            if self.retry_at <= self.deadline:
                print(
                    f"drone {self.settings.drone_id}: SuperNode not admitted ({self.refused}); "
                    f"retrying in {self.pause:.0f} s",
                    flush=True,
                )
            self.pause = min(2 * self.pause, 8.0)
        elif now >= self.retry_at:
            self.retry_at = None
            self.child = self._start()
        too_late = self.retry_at is not None and self.retry_at > self.deadline
        if not self.node and (now > self.deadline or too_late):
            raise DeployError(self.failure())

    def failure(self) -> str:
        """Why the SuperNode has not joined (the SuperLink's refusal, if it gave one)."""
        s = self.settings
        if self.refused is not None:
            return f"the SuperLink at {s.superlink} refused the SuperNode: {self.refused}"
        return (
            f"the SuperNode did not join the SuperLink at {s.superlink} within "
            f"{s.start_timeout:.0f} s"
        )


#: A SuperNode's line that says the SuperLink turned it away (its key, its certificate).
_REFUSAL = re.compile(r"activate|refused|denied|unauthori|authenticat|permission", re.I)


def _refusal(output: str, earlier: str | None = None) -> str:
    """The line of a SuperNode's output that says why it gave up: its last refusal line
    (:data:`_REFUSAL`); else ``earlier``, the reason an earlier attempt gave, when that was
    a refusal (an attempt that only failed to connect, as on a loaded machine, says less);
    else its last line that says something failed, or its last line."""
    lines = [ln.strip() for ln in output.splitlines() if ln.strip()]
    refusals = [ln for ln in lines if _REFUSAL.search(ln)]
    if refusals:
        return refusals[-1]
    if earlier is not None and _REFUSAL.search(earlier):
        return earlier
    failures = [ln for ln in lines if re.search(r"failed|error", ln, re.I)]
    return (failures or lines or ["(no output)"])[-1]


def _episode(link: Link, settings: DroneSettings, supernode: SuperNodeJoin) -> dict:
    """What the world simulates (asked until it answers; the SuperNode tended meanwhile)."""
    timeout = settings.start_timeout
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        supernode.tend()
        answer = link.request(EPISODE, timeout=1.0)
        if answer:
            return json.loads(answer)
        time.sleep(0.2)
    if supernode.refused is not None:  # the SuperLink's refusal says more than the silence
        raise DeployError(supernode.failure())
    hint = " (are both certificates signed by the same CA?)" if settings.tls_dir else ""
    raise DeployError(
        f"the world at {settings.connect[0]} did not answer within {timeout:.0f} s{hint}"
    )


def supernode_id(supernode: Child) -> bytes:
    """The node id the SuperLink gave this drone's SuperNode (from its log; empty until it
    has connected)."""
    found = _NODE_ID.findall(supernode.output())
    return found[-1].encode() if found else b""


def _serve(link: Link, drone: DroneProcess, supernode: SuperNodeJoin) -> None:
    d = drone.settings.drone_id

    def forward(_: str, payload: bytes) -> None:  # cloud's control -> autopilot
        link.put(ACTUATE.format(id=d), payload)

    link.subscribe(SENSE.format(id=d), lambda _, payload: drone.sensed.put(payload))
    link.subscribe(CONTROL.format(id=d), forward)
    link.serve(FLUSH.format(id=d), drone.flush)
    link.serve(RELOAD.format(id=d), drone.reload)
    link.serve(NODE.format(id=d), lambda _: supernode.node)  # empty until it has joined


def _loop(link: Link, drone: DroneProcess, supernode: SuperNodeJoin) -> None:
    key = PREDICTIONS.format(id=drone.settings.drone_id)
    try:
        while True:
            supernode.tend()
            try:
                payload = drone.sensed.get(timeout=0.5)
            except queue.Empty:
                if "world" not in link.alive():
                    print(f"drone {drone.settings.drone_id}: the world ended", flush=True)
                    return
                continue
            link.put(key, drone.predict(payload))
    finally:
        with drone.lock:
            if drone.record.steps:
                drone.record.to_log().save(drone.log_path)
