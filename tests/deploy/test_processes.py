"""Owned processes: a child's whole tree is stopped, even a helper detached into its own
session (as Flower's SuperLink detaches its SuperExec); ports in use are seen."""

import socket
import sys
import time

import psutil
from deploy_helpers import free_port_block

from dronefl.deploy.processes import Children, port_in_use, port_open

# A child that starts a grandchild in a new session (out of the child's process group),
# writes the grandchild's pid and sleeps.
_SPAWNER = """
import subprocess, sys, time
g = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(300)"], start_new_session=True)
open(sys.argv[1], "w").write(str(g.pid))
time.sleep(300)
"""


def test_children_stop_the_whole_tree_including_detached_helpers(tmp_path, monkeypatch):
    monkeypatch.delenv("DRONEFL_DEPLOY_OWNER", raising=False)
    pid_file = tmp_path / "grandchild.pid"
    with Children(tmp_path / "logs", grace=2.0) as children:
        child = children.start("spawner", [sys.executable, "-c", _SPAWNER, str(pid_file)])
        deadline = time.monotonic() + 60
        while not (pid_file.is_file() and pid_file.read_text()):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        grandchild = psutil.Process(int(pid_file.read_text()))
        assert grandchild.is_running()
    assert child.process.poll() is not None
    assert not grandchild.is_running() or grandchild.status() == psutil.STATUS_ZOMBIE
    assert (tmp_path / "logs" / "spawner.log").is_file()


def test_port_in_use_and_open():
    port = free_port_block(1)
    assert not port_in_use("127.0.0.1", port) and not port_open("127.0.0.1", port)
    with socket.socket() as server:
        server.bind(("127.0.0.1", port))
        server.listen()
        assert port_in_use("127.0.0.1", port) and port_open("127.0.0.1", port)
