"""The world process (``dronefl world``): the simulator standing in for vehicles and autopilots.

It owns the simulation clock. Each step ``k`` it publishes the cloud's telemetry (every
drone's autopilot state) and each drone's sensors (noisy odometry and the projection
detector's boxes of its camera view: the same numbers, drawn from the same seeded streams in
the same order, as in ``dronefl track``), then waits until the cloud releases the step (after
planning, and after an FL round when one is due: the world pauses while it runs) and applies
each drone's control, which reaches it through that drone's process. A drone that is gone
(no liveliness) or whose control is late by more than ``grace_ms`` holds position: its
autopilot brakes (``u = -v / dt``, within the acceleration bound), and the step is counted.

It writes ``world.npz`` (true target and drone states of every step, which drones' controls
were missing, the wall time of every step) into ``out``.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dronefl.config import load_scenario
from dronefl.deploy.certs import CertificateFolder
from dronefl.deploy.link import (
    ACTUATE,
    EPISODE,
    RELEASE,
    SENSE,
    TELEMETRY,
    WORLD,
    Link,
    LinkConfig,
    check_endpoint,
)
from dronefl.deploy.messages import SenseMessage, TelemetryMessage, decode_release
from dronefl.io import atomic_savez
from dronefl.perception import make_detector
from dronefl.sim.world import World
from dronefl.wire import ControlMessage, WireError


class WorldError(RuntimeError):
    """The episode could not go on (the cloud never came or left)."""


@dataclass(frozen=True)
class WorldSettings:
    """One simulated episode: ``duration`` s of ``scenario`` in ``environment`` with ``seed``.

    ``listen`` the Zenoh endpoint (``host:port``); ``tls_dir`` the certificate folder (empty:
    plain TCP, no authentication); ``start_timeout`` s to wait for the cloud;
    ``stall_timeout`` s one step may take (an FL round included); ``grace_ms`` wall ms a
    control may trail the cloud's release.
    """

    scenario: str
    out: Path
    seed: int = 0
    duration: float = 120.0
    environment: str = "orchard"
    listen: str = "127.0.0.1:7440"
    tls_dir: str = ""
    start_timeout: float = 120.0
    stall_timeout: float = 600.0
    grace_ms: float = 150.0

    def __post_init__(self) -> None:
        check_endpoint(self.listen, "--listen")

    def link(self, drone_ids: tuple[int, ...]) -> LinkConfig:
        """The world's link in a deployment flying ``drone_ids``."""
        tls = CertificateFolder(Path(self.tls_dir)).zenoh(WORLD) if self.tls_dir else None
        return LinkConfig((self.listen,), (), tls, drone_ids)


class _Mailbox:
    """The cloud's releases and the drones' controls (filled on Zenoh threads)."""

    def __init__(self) -> None:
        self.released = -1
        self.controls: dict[int, ControlMessage] = {}
        self.changed = threading.Condition()

    def on_release(self, _: str, payload: bytes) -> None:
        with self.changed:
            self.released = max(self.released, decode_release(payload))
            self.changed.notify_all()

    def on_control(self, key: str, payload: bytes) -> None:
        try:
            message = ControlMessage.decode(payload)
        except WireError:
            return
        if message.drone_id != int(key.rsplit("/", 1)[1]):
            return
        with self.changed:
            self.controls[message.drone_id] = message
            self.changed.notify_all()


def run_world(settings: WorldSettings) -> Path:
    """Run the episode's world side; returns the path of ``world.npz``."""
    scenario = load_scenario(settings.scenario)
    world = World(scenario, settings.environment, settings.seed)
    detector = make_detector("projection", world)
    n_steps = int(round(settings.duration * scenario.rate_hz))
    ids = scenario.drone_ids
    m, n = len(ids), len(scenario.targets)
    truth = {
        "target_position": np.zeros((n_steps + 1, n, 2)),
        "drone_position": np.zeros((n_steps + 1, m, 2)),
        "drone_velocity": np.zeros((n_steps + 1, m, 2)),
    }
    missing = np.zeros((n_steps, m), dtype=bool)
    step_ms = np.zeros(n_steps)
    info = json.dumps(
        {
            "scenario": scenario.name,
            "environment": settings.environment,
            "seed": settings.seed,
            "steps": n_steps,
            "dt": scenario.dt,
        }
    ).encode()
    mailbox = _Mailbox()
    with Link(settings.link(ids)) as link:
        link.watch_alive()
        link.subscribe(RELEASE, mailbox.on_release)
        for d in ids:  # one key per drone: each drone may put on its own only
            link.subscribe(ACTUATE.format(id=d), mailbox.on_control)
        link.announce("world")
        link.serve(EPISODE, lambda _: info)
        print(f"world: {scenario.name}, {n_steps} steps; waiting for the cloud", flush=True)
        if link.wait_alive({"cloud"}, settings.start_timeout):
            raise WorldError(f"the cloud did not start within {settings.start_timeout:.0f} s")
        for k in range(n_steps):
            _record(truth, k, world)
            started = time.perf_counter()
            telemetry = TelemetryMessage(k, world.t, world.drone_states())
            link.put(TELEMETRY, telemetry.encode())
            for odometry, view in zip(world.odometry(), world.camera_views(), strict=True):
                sense = SenseMessage(k, odometry, detector.detect(view))
                link.put(SENSE.format(id=view.drone_id), sense.encode())
            _wait_release(link, mailbox, k, settings.stall_timeout)
            commands = _controls(link, mailbox, k, world, settings.grace_ms / 1000)
            missing[k] = [c is None for c in commands]
            velocity = world.drones.velocity
            world.step(
                np.array(
                    [
                        c if c is not None else -velocity[i] / world.dt  # hold position
                        for i, c in enumerate(commands)
                    ]
                )
            )
            step_ms[k] = 1000 * (time.perf_counter() - started)
            if (k + 1) % 25 == 0:
                print(f"world: step {k + 1}/{n_steps} t={world.t:.1f} s", flush=True)
        _record(truth, n_steps, world)
    path = Path(settings.out) / "world.npz"
    atomic_savez(
        path,
        missing_control=missing,
        step_ms=step_ms,
        seed=np.array(settings.seed),
        environment=np.array(settings.environment),
        **truth,
    )
    print(f"world: done, wrote {path}", flush=True)
    return path


def _record(truth: dict[str, np.ndarray], k: int, world: World) -> None:
    truth["target_position"][k] = world.targets.position
    truth["drone_position"][k] = world.drones.position
    truth["drone_velocity"][k] = world.drones.velocity


def _wait_release(link: Link, mailbox: _Mailbox, k: int, stall: float) -> None:
    deadline = time.monotonic() + stall
    with mailbox.changed:
        while mailbox.released < k:
            if "cloud" not in link.alive():
                # The cloud's last release may still be on its way when its liveliness token
                # goes (the two travel separately): give it a moment before calling it gone.
                mailbox.changed.wait_for(lambda: mailbox.released >= k, timeout=2.0)
                if mailbox.released >= k:
                    return
                raise WorldError(f"the cloud left at step {k}")
            if time.monotonic() > deadline:
                raise WorldError(f"step {k} was not released within {stall:.0f} s")
            mailbox.changed.wait(0.2)


def _controls(
    link: Link, mailbox: _Mailbox, k: int, world: World, grace: float
) -> list[tuple[float, float] | None]:
    """Each drone's control of step ``k`` (None: missing), waiting up to ``grace`` s for the
    live drones' controls."""
    ids = world.scenario.drone_ids
    deadline = time.perf_counter() + grace
    with mailbox.changed:
        while True:
            have = {d for d, c in mailbox.controls.items() if c.step == k}
            alive = {d for d in ids if f"drone/{d}" in link.alive()}
            left = deadline - time.perf_counter()
            if alive <= have or left <= 0:
                break
            mailbox.changed.wait(left)
        return [
            mailbox.controls[d].acceleration if d in have else None  # type: ignore[misc]
            for d in ids
        ]
