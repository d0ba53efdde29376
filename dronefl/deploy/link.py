"""The per-step link over Zenoh: key expressions, session configuration, byte counting.

Every process opens one Zenoh session in *peer* mode with multicast scouting off and explicit
endpoints: the world and the cloud listen (one ``host:port`` each), every other process
connects to both, so each message travels one direct TCP (or TLS) hop. On several hosts the
same endpoints are the hosts' addresses; a Zenoh router in between needs no code change.

Which process is up is Zenoh *liveliness*: each declares a token under :data:`ALIVE` that
vanishes when its session closes or its process dies, so the others notice a dead drone
within a TCP timeout instead of waiting for it.

TLS (``LinkTls``): every link is ``tls/host:port`` with mutual authentication: both ends
present a certificate signed by the deployment's CA and check the other's against it.
"""

from __future__ import annotations

import json
import threading
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import zenoh

#: Key expressions (``{id}``: a drone id).
SENSE = "dronefl/world/sense/{id}"  # world -> drone: odometry + detections of step k
ACTUATE = "dronefl/world/actuate/{id}"  # drone -> world: the control it received
TELEMETRY = "dronefl/world/telemetry"  # world -> cloud: autopilot states of step k
EPISODE = "dronefl/world/episode"  # queryable: what the world simulates (JSON)
PREDICTIONS = "dronefl/drone/{id}/predictions"  # drone -> cloud (dronefl.wire)
CONTROL = "dronefl/drone/{id}/control"  # cloud -> drone (dronefl.wire)
NODE = "dronefl/drone/{id}/node"  # queryable: the id of the drone's SuperNode
FLUSH = "dronefl/drone/{id}/flush"  # queryable: write the onboard record and labels
RELOAD = "dronefl/drone/{id}/reload"  # queryable: load the new global model from disk
RELEASE = "dronefl/cloud/release"  # cloud -> world: step k is planned, move on
ALIVE = "dronefl/alive/{role}"  # liveliness: world, cloud, drone/<id>
CONNECT_RETRY = {"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2}


class LinkError(RuntimeError):
    """The link could not be opened or a peer did not answer in time."""


@dataclass(frozen=True)
class LinkTls:
    """Files of one process's TLS identity: the deployment's CA certificate and this
    process's certificate and private key (PEM), all signed by that CA."""

    ca: Path
    certificate: Path
    key: Path

    def check(self) -> None:
        """Raise :class:`LinkError` naming the first missing file."""
        for name in ("ca", "certificate", "key"):
            path = Path(getattr(self, name))
            if not path.is_file():
                raise LinkError(f"Zenoh TLS {name}: {path} does not exist")


@dataclass(frozen=True)
class LinkConfig:
    """Endpoints (``host:port``) this process listens on and connects to; TLS when ``tls``."""

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    tls: LinkTls | None = None

    @property
    def protocol(self) -> str:
        return "tls" if self.tls is not None else "tcp"

    def locators(self, endpoints: tuple[str, ...]) -> list[str]:
        return [f"{self.protocol}/{e}" for e in endpoints]

    def zenoh_config(self) -> zenoh.Config:
        """The session configuration: peer mode, no multicast scouting, explicit endpoints.

        A peer not yet listening (or gone after a dropout) is retried every 0.1 s, backing
        off to every 0.5 s, instead of Zenoh's default 1-4 s: a process that starts a few
        seconds after the one connecting to it is otherwise seen up to 4 s late."""
        config = zenoh.Config()
        values: dict[str, object] = {
            "mode": "peer",
            "scouting/multicast/enabled": False,
            "listen/endpoints": self.locators(self.listen),
            "connect/endpoints": self.locators(self.connect),
            "connect/retry": CONNECT_RETRY,
        }
        if self.tls is not None:
            self.tls.check()
            tls = "transport/link/tls/"
            values |= {
                tls + "root_ca_certificate": str(self.tls.ca),
                tls + "listen_certificate": str(self.tls.certificate),
                tls + "listen_private_key": str(self.tls.key),
                tls + "connect_certificate": str(self.tls.certificate),
                tls + "connect_private_key": str(self.tls.key),
                tls + "enable_mtls": True,
            }
        for key, value in values.items():
            config.insert_json5(key, json.dumps(value))
        return config


class Link:
    """One process's Zenoh session (a context manager: closed on every exit path).

    :attr:`published` counts the payload bytes this process put, by key expression.
    """

    def __init__(self, config: LinkConfig) -> None:
        self.config = config
        try:
            self.session = zenoh.open(config.zenoh_config())
        except zenoh.ZError as exc:
            raise LinkError(f"Zenoh: cannot open a session on {config.listen}: {exc}") from None
        self.published: dict[str, int] = defaultdict(int)
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._keep: list[object] = []
        self._alive: set[str] = set()
        self._alive_changed = threading.Condition()

    def __enter__(self) -> Link:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._keep.clear()
        self.session.close()

    def put(self, key: str, payload: bytes) -> int:
        """Publish ``payload`` on ``key``; returns (and counts) its size in bytes."""
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self._publishers[key] = self.session.declare_publisher(key)
        publisher.put(payload)
        self.published[key] += len(payload)
        return len(payload)

    def subscribe(self, key: str, callback: Callable[[str, bytes], None]) -> None:
        """Call ``callback(key, payload)`` (on a Zenoh thread) for every sample on ``key``."""
        self._keep.append(
            self.session.declare_subscriber(
                key, lambda sample: callback(str(sample.key_expr), sample.payload.to_bytes())
            )
        )

    def serve(self, key: str, answer: Callable[[bytes], bytes]) -> None:
        """Answer every query on ``key`` with ``answer(payload)``."""

        def reply(query: zenoh.Query) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            query.reply(key, answer(payload))

        self._keep.append(self.session.declare_queryable(key, reply))

    def request(self, key: str, payload: bytes = b"", timeout: float = 5.0) -> bytes | None:
        """The first answer to a query on ``key``, or ``None`` if nobody answered in time."""
        self.published[key] += len(payload)
        for reply in self.session.get(key, payload=payload, timeout=timeout):
            if reply.ok is not None:
                return reply.ok.payload.to_bytes()
        return None

    def announce(self, role: str) -> None:
        """Declare this process alive as ``role`` (``world``, ``cloud``, ``drone/<id>``)."""
        self._keep.append(self.session.liveliness().declare_token(ALIVE.format(role=role)))

    def watch_alive(self) -> None:
        """Track which roles are alive (:meth:`alive`, :meth:`wait_alive`)."""
        prefix = ALIVE.format(role="")

        def changed(sample: zenoh.Sample) -> None:
            role = str(sample.key_expr)[len(prefix) :]
            with self._alive_changed:
                if sample.kind == zenoh.SampleKind.PUT:
                    self._alive.add(role)
                else:
                    self._alive.discard(role)
                self._alive_changed.notify_all()

        self._keep.append(
            self.session.liveliness().declare_subscriber(
                prefix + "**", history=True, handler=changed
            )
        )

    def alive(self) -> set[str]:
        """Roles alive now."""
        with self._alive_changed:
            return set(self._alive)

    def wait_alive(self, roles: set[str], timeout: float) -> set[str]:
        """Wait until every role in ``roles`` is alive; returns those still missing."""
        deadline = time.monotonic() + timeout
        with self._alive_changed:
            while not roles <= self._alive and time.monotonic() < deadline:
                self._alive_changed.wait(min(0.2, max(0.0, deadline - time.monotonic())))
            return roles - self._alive
