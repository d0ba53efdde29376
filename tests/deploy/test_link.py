"""The Zenoh link on 127.0.0.1: delivery, byte counting, liveliness, queries, mutual TLS."""

import threading
import time
from pathlib import Path

import pytest
from deploy_helpers import free_port_block

from dronefl.deploy.certs import make_certificates
from dronefl.deploy.link import ACTUATE, EPISODE, Link, LinkConfig, LinkTls


def _pair(listen: LinkConfig, connect: LinkConfig):
    return Link(listen), Link(connect)


def _exchange(
    server: Link, client: Link, put: str = "t/x", role: str = "drone/7"
) -> tuple[list[bytes], int]:
    """Send "hello" on ``put`` until it arrives, the client announced as ``role``; returns
    what arrived and how many were sent."""
    got, arrived = [], threading.Event()
    server.subscribe(put, lambda _, payload: (got.append(payload), arrived.set()))
    client.announce(role)
    server.watch_alive()
    assert server.wait_alive({role}, timeout=10.0) == set()
    deadline, sent = time.monotonic() + 10, 0
    while not got and time.monotonic() < deadline:  # the subscription may take a moment
        sent += 1
        client.put(put, b"hello")
        arrived.wait(0.2)
    return got, sent


def test_publish_subscribe_query_and_liveliness_over_tcp():
    port = free_port_block(2)
    server, client = _pair(
        LinkConfig((f"127.0.0.1:{port}",)), LinkConfig((), (f"127.0.0.1:{port}",))
    )
    with server, client:
        server.serve("t/q", lambda payload: b"echo:" + payload)
        got, sent = _exchange(server, client)
        assert got[0] == b"hello"
        assert client.published["t/x"] == 5 * sent  # the payload bytes put, 5 each
        assert client.request("t/q", b"42", timeout=5.0) == b"echo:42"
        assert client.request("t/nobody", timeout=0.5) is None
    # The client's session is closed: its token vanishes from a third peer's view.
    with Link(LinkConfig((f"127.0.0.1:{port + 1}",))) as observer:
        observer.watch_alive()
        assert "drone/7" not in observer.alive()


def test_mutual_tls_admits_the_ca_s_certificates_only(tmp_path):
    certs = make_certificates(tmp_path / "ours", [1])
    other = make_certificates(tmp_path / "theirs", [1])
    port = free_port_block(2)
    world = LinkConfig((f"127.0.0.1:{port}",), (), certs.zenoh("world"), (1,))
    with Link(world) as server:
        server.serve(EPISODE, lambda _: b"case1")
        drone = LinkConfig((), (f"127.0.0.1:{port}",), certs.zenoh("drone-1"), (1,))
        with Link(drone) as client:
            got, _ = _exchange(server, client, ACTUATE.format(id=1), "drone/1")
            assert got[0] == b"hello"
            assert client.request(EPISODE, timeout=5.0) == b"case1"
        theirs = other.zenoh("drone-1")
        stranger = LinkTls(certs.ca, theirs.certificate, theirs.key, "drone-1")
        with Link(LinkConfig((), (f"127.0.0.1:{port}",), stranger, (1,))) as intruder:
            intruder.announce("drone/1")
            server.watch_alive()
            assert server.wait_alive({"drone/1"}, timeout=3.0) == {"drone/1"}


def test_missing_tls_file_is_named():
    tls = LinkTls(tmp := Path("/nonexistent/ca.crt"), tmp, tmp, "world")
    with pytest.raises(FileNotFoundError, match="ca: /nonexistent/ca.crt does not exist"):
        Link(LinkConfig(("127.0.0.1:1",), (), tls))


def test_a_certificate_of_another_role_is_named(tmp_path):
    certs = make_certificates(tmp_path, [1])
    world = certs.zenoh("world")
    tls = LinkTls(world.ca, world.certificate, world.key, "cloud")
    with pytest.raises(ValueError, match="zenoh-world.crt names 'world', not 'cloud'"):
        Link(LinkConfig(("127.0.0.1:1",), (), tls))
