"""Access control on the per-step link: each process lets each peer, known by the common name
of its certificate, send only what that peer's role sends. A compromised drone 2 (one that
drops its own rules) can neither speak for drone 1 nor for the cloud; a peer without a
certificate of the deployment's CA cannot connect at all."""

import threading
import time

import zenoh
from deploy_helpers import free_port_block

from dronefl.deploy.access import access_control
from dronefl.deploy.certs import make_certificates
from dronefl.deploy.link import (
    ACTUATE,
    ALIVE,
    CONTROL,
    FLUSH,
    NODE,
    PREDICTIONS,
    RELEASE,
    SENSE,
    TELEMETRY,
    Link,
    LinkConfig,
    LinkTls,
    exchanges,
)

DRONES = (1, 2)
#: How long a forged message is given to arrive after the genuine ones have, s.
SILENCE_S = 1.0


def _allowed(role: str, peer: str, flow: str, kind: str) -> set[str]:
    """The key expressions on which ``role``'s session lets ``peer`` exchange ``kind``."""
    acl = access_control(role, exchanges(DRONES))
    return {
        key
        for rule in acl["rules"]
        if rule["id"] == f"{peer} {flow} {kind}"
        for key in rule["key_exprs"]
    }


def test_each_role_sends_only_its_own_keys():
    acl = access_control("drone-2", exchanges(DRONES))
    assert [s["cert_common_names"] for s in acl["subjects"]] == [["cloud"], ["world"]]
    assert acl["default_permission"] == "deny"
    # Drone 2 puts its predictions to the cloud and its control to its autopilot (the world),
    # declares its own token, answers the cloud's queries about itself, hears its own
    # sensors and controls.
    assert _allowed("drone-2", "cloud", "egress", "put") == {"dronefl/drone/2/predictions"}
    assert _allowed("drone-2", "world", "egress", "put") == {"dronefl/world/actuate/2"}
    assert _allowed("drone-2", "world", "egress", "liveliness_token") == {"dronefl/alive/drone/2"}
    assert _allowed("drone-2", "cloud", "egress", "reply") == {
        "dronefl/drone/2/node", "dronefl/drone/2/flush", "dronefl/drone/2/reload"
    }  # fmt: skip
    assert _allowed("drone-2", "world", "ingress", "put") == {"dronefl/world/sense/2"}
    assert _allowed("drone-2", "cloud", "ingress", "put") == {"dronefl/drone/2/control"}
    assert _allowed("drone-2", "cloud", "ingress", "query") == {
        "dronefl/drone/2/node", "dronefl/drone/2/flush", "dronefl/drone/2/reload"
    }  # fmt: skip
    # The world hears drone i's control on drone i's key only, releases from the cloud only;
    # the cloud hears predictions from their drone and telemetry from the world only.
    assert _allowed("world", "drone-1", "ingress", "put") == {"dronefl/world/actuate/1"}
    assert _allowed("world", "cloud", "ingress", "put") == {"dronefl/cloud/release"}
    assert _allowed("cloud", "drone-1", "ingress", "put") == {"dronefl/drone/1/predictions"}
    assert _allowed("cloud", "world", "ingress", "put") == {"dronefl/world/telemetry"}
    assert _allowed("cloud", "drone-2", "ingress", "liveliness_token") == {"dronefl/alive/drone/2"}
    # The launcher only watches.
    launcher = access_control("world", exchanges(DRONES))["policies"]
    rules = next(p["rules"] for p in launcher if p["id"] == "launcher")
    assert sorted(rules) == [
        "launcher egress liveliness_token",
        "launcher ingress declare_liveliness_subscriber",
        "launcher ingress liveliness_query",
    ]


class _Heard:
    """Payloads heard by key (filled on Zenoh threads)."""

    def __init__(self) -> None:
        self.payloads: dict[str, list[bytes]] = {}
        self.changed = threading.Condition()

    def __call__(self, key: str, payload: bytes) -> None:
        with self.changed:
            self.payloads.setdefault(key, []).append(payload)
            self.changed.notify_all()

    def on(self, key: str) -> list[bytes]:
        with self.changed:
            return list(self.payloads.get(key, []))


def _compromised(config: LinkConfig) -> zenoh.Session:
    """A session with ``config``'s identity that ignores its own access control."""
    zenoh_config = config.zenoh_config()
    zenoh_config.insert_json5("access_control/enabled", "false")
    return zenoh.open(zenoh_config)


def _replies(session: zenoh.Session, key: str, timeout: float) -> list[bytes]:
    """Every answer to a query on ``key`` (from every queryable the session knows of)."""
    replies = session.get(
        key,
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=timeout,
    )
    return [r.ok.payload.to_bytes() for r in replies if r.ok]


def _until(condition, timeout: float, every: float, act) -> bool:
    """Call ``act()`` every ``every`` s until ``condition()`` holds; False after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return False
        act()
        time.sleep(every)
    return True


def test_a_compromised_drone_cannot_speak_for_another_drone_or_the_cloud(tmp_path):
    certs = make_certificates(tmp_path, DRONES)
    port = free_port_block(2)
    at = (f"127.0.0.1:{port}", f"127.0.0.1:{port + 1}")
    world_config = LinkConfig((at[0],), (), certs.zenoh("world"), DRONES)
    cloud_config = LinkConfig((at[1],), (), certs.zenoh("cloud"), DRONES)
    drone_1_config = LinkConfig((), at, certs.zenoh("drone-1"), DRONES)
    heard, flushed = _Heard(), []
    with Link(world_config) as world, Link(cloud_config) as cloud, Link(drone_1_config) as drone_1:
        for key in (ACTUATE.format(id=1), ACTUATE.format(id=2), RELEASE, CONTROL.format(id=2)):
            world.subscribe(key, heard)
        for key in (PREDICTIONS.format(id=1), PREDICTIONS.format(id=2), TELEMETRY):
            cloud.subscribe(key, heard)
        for key in (CONTROL.format(id=1), SENSE.format(id=1)):
            drone_1.subscribe(key, heard)
        drone_1.serve(NODE.format(id=1), lambda _: b"node of drone 1")
        drone_1.serve(FLUSH.format(id=1), lambda labels: flushed.append(labels) or b"ok")
        world.watch_alive()
        cloud.watch_alive()

        intruder = _compromised(LinkConfig((), at, certs.zenoh("drone-2"), DRONES))
        keep = []
        try:
            keep += [
                intruder.declare_queryable(NODE.format(id=1), lambda q: q.reply(q.key_expr, b"x")),
                intruder.declare_queryable(NODE.format(id=2), lambda q: q.reply(q.key_expr, b"2")),
            ]
            keep += [
                intruder.liveliness().declare_token(ALIVE.format(role=role))
                for role in ("cloud", "world", "drone/1", "drone/2")
            ]
            own = (PREDICTIONS.format(id=2), ACTUATE.format(id=2))
            forged = (
                PREDICTIONS.format(id=1),  # as drone 1, to the cloud
                ACTUATE.format(id=1),  # as drone 1, to drone 1's autopilot
                CONTROL.format(id=1),  # as the cloud, to drone 1
                CONTROL.format(id=2),  # as the cloud
                RELEASE,  # as the cloud, to the world
                TELEMETRY,  # as the world, to the cloud
                SENSE.format(id=1),  # as the world, to drone 1
            )

            def publish() -> None:
                for key in own + forged:
                    intruder.put(key, b"drone 2")

            # Its own publications arrive; then a second more of the forged ones.
            assert _until(lambda: all(heard.on(k) for k in own), 10.0, 0.05, publish)
            _until(lambda: False, SILENCE_S, 0.05, publish)
            assert {k: heard.on(k) for k in forged} == {k: [] for k in forged}

            # Its own queryable answers the cloud; drone 1's is drone 1's alone.
            assert _replies(cloud.session, NODE.format(id=2), 5.0) == [b"2"]
            assert _replies(cloud.session, NODE.format(id=1), 5.0) == [b"node of drone 1"]
            # It cannot write labels into drone 1's training data; the cloud can.
            assert _replies(intruder, FLUSH.format(id=1), SILENCE_S) == []
            assert flushed == []
            assert cloud.request(FLUSH.format(id=1), b"labels", 5.0) == b"ok"
            assert flushed == [b"labels"]

            # Its own token is seen; the cloud's, the world's and drone 1's it cannot declare.
            assert world.wait_alive({"drone/2"}, 10.0) == set()
            assert cloud.wait_alive({"drone/2"}, 10.0) == set()
            assert world.alive() == {"drone/2"} and cloud.alive() == {"drone/2"}
        finally:
            for declared in keep:
                declared.undeclare()
            intruder.close()


def test_a_peer_without_a_certificate_of_our_ca_cannot_connect(tmp_path):
    ours = make_certificates(tmp_path / "ours", DRONES)
    theirs = make_certificates(tmp_path / "theirs", DRONES).zenoh("drone-2")
    port = free_port_block(1)
    at = (f"127.0.0.1:{port}",)
    heard = _Heard()
    with Link(LinkConfig(at, (), ours.zenoh("world"), DRONES)) as world:
        world.subscribe(ACTUATE.format(id=2), heard)
        world.watch_alive()
        # Drone 2's key and token, from a plain TCP peer and from a peer whose certificate
        # (common name drone-2, and trusting our CA) another CA signed.
        stranger = LinkTls(ours.ca, theirs.certificate, theirs.key, "drone-2")
        outsiders = [
            _compromised(LinkConfig((), at, stranger, DRONES)),
            zenoh.open(LinkConfig((), at).zenoh_config()),
        ]
        tokens = [s.liveliness().declare_token(ALIVE.format(role="drone/2")) for s in outsiders]
        try:
            with Link(LinkConfig((), at, ours.zenoh("drone-2"), DRONES)) as drone_2:

                def publish() -> None:
                    drone_2.put(ACTUATE.format(id=2), b"drone 2")
                    for session in outsiders:
                        session.put(ACTUATE.format(id=2), b"outsider")

                assert _until(lambda: heard.on(ACTUATE.format(id=2)), 10.0, 0.05, publish)
                _until(lambda: False, SILENCE_S, 0.05, publish)
                assert set(heard.on(ACTUATE.format(id=2))) == {b"drone 2"}
            # Drone 2 gone, its token went with it: the outsiders' never arrived.
            deadline = time.monotonic() + 10.0
            while "drone/2" in world.alive() and time.monotonic() < deadline:
                time.sleep(0.05)
            assert world.alive() == set()
        finally:
            for token in tokens:
                token.undeclare()
            for session in outsiders:
                session.close()


def test_a_compromised_drone_cannot_read_another_drone_s_sensors_or_control(tmp_path):
    """What the world and the cloud send drone 1 (sensors, control) and the cloud (telemetry)
    reaches them, never a drone 2 that subscribes to it with its own rules dropped."""
    certs = make_certificates(tmp_path, DRONES)
    port = free_port_block(2)
    at = (f"127.0.0.1:{port}", f"127.0.0.1:{port + 1}")
    world_config = LinkConfig((at[0],), (), certs.zenoh("world"), DRONES)
    cloud_config = LinkConfig((at[1],), (at[0],), certs.zenoh("cloud"), DRONES)
    drone_1_config = LinkConfig((), at, certs.zenoh("drone-1"), DRONES)
    genuine, stolen = _Heard(), _Heard()
    secret = {SENSE.format(id=1): "world", CONTROL.format(id=1): "cloud", TELEMETRY: "world"}
    with Link(world_config) as world, Link(cloud_config) as cloud, Link(drone_1_config) as drone_1:
        drone_1.subscribe(SENSE.format(id=1), genuine)
        drone_1.subscribe(CONTROL.format(id=1), genuine)
        cloud.subscribe(TELEMETRY, genuine)
        intruder = _compromised(LinkConfig((), at, certs.zenoh("drone-2"), DRONES))
        subscribers = [
            intruder.declare_subscriber(
                key, lambda sample: stolen(str(sample.key_expr), sample.payload.to_bytes())
            )
            for key in secret
        ]
        senders = {"world": world, "cloud": cloud}
        try:

            def publish() -> None:
                for key, sender in secret.items():
                    senders[sender].put(key, b"secret")

            assert _until(lambda: all(genuine.on(k) for k in secret), 10.0, 0.05, publish)
            _until(lambda: False, SILENCE_S, 0.05, publish)
            assert stolen.payloads == {}
        finally:
            for subscriber in subscribers:
                subscriber.undeclare()
            intruder.close()
