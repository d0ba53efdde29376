"""The per-step link over Zenoh: key expressions, who sends on each, session configuration.

Every process opens one Zenoh session in *peer* mode with multicast and gossip scouting off
and explicit endpoints: the world and the cloud listen (one ``host:port`` each), every other
process connects to both, so each message travels one direct TCP (or TLS) hop and no process
learns of, or connects to, any other. Peers do not forward one another's messages. On several
hosts the same endpoints are the hosts' addresses.

Which process is up is Zenoh *liveliness*: each declares a token under :data:`ALIVE` that
vanishes when its session closes or its process dies, so the others notice a dead drone
within a TCP timeout instead of waiting for it.

TLS (:class:`LinkTls`): every link is ``tls/host:port`` with mutual authentication: both ends
present a certificate signed by the deployment's CA and check the other's against it. Each
certificate names its process's role as its common name (:func:`roles`), and each session
allows each peer, by that name, exactly the messages of :func:`exchanges` between their two
roles (:mod:`dronefl.deploy.access`); everything else is denied. Without TLS there is no
identity to check, and any process that reaches a port may say anything.
"""

from __future__ import annotations

import json
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import zenoh
from cryptography import x509
from cryptography.x509.oid import NameOID

from dronefl.deploy.access import Message, access_control, liveliness, publication, query

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

#: Roles, the common names of the processes' certificates (and drone ``i``'s, ``drone-<i>``).
WORLD, CLOUD, LAUNCHER = "world", "cloud", "launcher"


def drone_role(drone_id: int) -> str:
    """The role of drone ``drone_id`` (its certificate's common name)."""
    return f"drone-{drone_id}"


def roles(drone_ids: Iterable[int]) -> list[str]:
    """Every role of a deployment flying ``drone_ids``."""
    return [WORLD, CLOUD, LAUNCHER, *(drone_role(d) for d in drone_ids)]


def exchanges(drone_ids: Iterable[int]) -> list[Message]:
    """Every message a deployment flying ``drone_ids`` sends, by sender and receiver role:
    the world sends each drone its sensors, the cloud its telemetry, and answers a drone's
    ``episode`` query; drone ``i`` sends the cloud its predictions, the world (its autopilot)
    its control, and answers the cloud's queries ``node``, ``flush`` and ``reload`` of drone
    ``i``; the cloud sends drone ``i`` its control and the world its releases. The world, the
    cloud and each drone show their liveliness token to every process linked to them; the
    launcher, linked to the world and the cloud, only watches."""
    messages = publication(WORLD, CLOUD, TELEMETRY) + publication(CLOUD, WORLD, RELEASE)
    tokens = {WORLD: ALIVE.format(role="world"), CLOUD: ALIVE.format(role="cloud")}
    links = [(WORLD, CLOUD), (WORLD, LAUNCHER), (CLOUD, LAUNCHER)]
    for d in drone_ids:
        drone = drone_role(d)
        tokens[drone] = ALIVE.format(role=f"drone/{d}")
        links += [(WORLD, drone), (CLOUD, drone)]
        messages += publication(WORLD, drone, SENSE.format(id=d))
        messages += publication(drone, WORLD, ACTUATE.format(id=d))
        messages += query(WORLD, drone, EPISODE)
        messages += publication(drone, CLOUD, PREDICTIONS.format(id=d))
        messages += publication(CLOUD, drone, CONTROL.format(id=d))
        for key in (NODE, FLUSH, RELOAD):
            messages += query(drone, CLOUD, key.format(id=d))
    watched = ALIVE.format(role="**")
    for a, b in links:
        for owner, watcher in ((a, b), (b, a)):
            if owner in tokens:
                messages += liveliness(owner, watcher, tokens[owner], watched)
    return messages


def check_endpoint(endpoint: str, option: str) -> None:
    """``ValueError`` naming ``option`` unless ``endpoint`` is ``host:port`` (port 1-65535)."""
    host, _, port = endpoint.rpartition(":")
    if not (host and port.isdigit() and 1 <= int(port) <= 65535):
        raise ValueError(f"{option}: {endpoint!r} is not host:port (a port in 1-65535)")


class LinkError(RuntimeError):
    """The link could not be opened or a peer did not answer in time."""


@dataclass(frozen=True)
class LinkTls:
    """One process's TLS identity: the deployment's CA certificate, this process's
    certificate and private key (PEM, signed by that CA), and its ``role``, the common name
    its certificate must carry (the other processes know it by that name)."""

    ca: Path
    certificate: Path
    key: Path
    role: str

    def check(self) -> None:
        """``FileNotFoundError`` naming the first missing file; ``ValueError`` if the
        certificate is not one of :attr:`role`."""
        for name in ("ca", "certificate", "key"):
            path = Path(getattr(self, name))
            if not path.is_file():
                raise FileNotFoundError(f"Zenoh TLS {name}: {path} does not exist")
        name = common_name(Path(self.certificate))
        if name != self.role:
            raise ValueError(
                f"Zenoh TLS certificate: {self.certificate} names {name!r}, not {self.role!r} "
                "(make the folder again with `dronefl deploy certs`)"
            )


def common_name(path: Path) -> str:
    """The subject common name of the PEM certificate ``path`` (empty if it has none);
    ``ValueError`` naming the file if it holds no certificate."""
    try:
        certificate = x509.load_pem_x509_certificate(path.read_bytes())
    except ValueError:
        raise ValueError(f"Zenoh TLS certificate: {path} is not a PEM certificate") from None
    names = certificate.subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    return str(names[0].value) if names else ""


@dataclass(frozen=True)
class LinkConfig:
    """Endpoints (``host:port``) this process listens on and connects to; with ``tls``
    (this process's identity), mutual TLS and the access control of its role in a deployment
    flying ``drone_ids`` (:func:`exchanges`)."""

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    tls: LinkTls | None = None
    drone_ids: tuple[int, ...] = ()

    @property
    def protocol(self) -> str:
        return "tls" if self.tls is not None else "tcp"

    def locators(self, endpoints: tuple[str, ...]) -> list[str]:
        return [f"{self.protocol}/{e}" for e in endpoints]

    def zenoh_config(self) -> zenoh.Config:
        """The session configuration: peer mode, no multicast or gossip scouting, explicit
        endpoints; with TLS, mutual authentication and access control.

        A peer not yet listening (or gone after a dropout) is retried every 0.1 s, backing
        off to every 0.5 s, instead of Zenoh's default 1-4 s: a process that starts a few
        seconds after the one connecting to it is otherwise seen up to 4 s late."""
        config = zenoh.Config()
        values: dict[str, object] = {
            "mode": "peer",
            "scouting/multicast/enabled": False,
            "scouting/gossip/enabled": False,
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
                "access_control": access_control(self.tls.role, exchanges(self.drone_ids)),
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
