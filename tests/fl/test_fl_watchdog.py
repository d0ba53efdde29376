"""A ClientApp's process ends when the process that started it dies (dronefl.fl.watchdog)."""

import os
import signal
import subprocess
import sys
import time

import psutil

#: A parent that starts a child running the watchdog, prints the child's pid, then waits.
PARENT = """
import subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c", sys.argv[1]])
print(child.pid, flush=True)
time.sleep(600)
"""
CHILD = (
    "import time; from dronefl.fl.watchdog import exit_with_parent; "
    "exit_with_parent(0.05); exit_with_parent(0.05); time.sleep(600)"
)


def test_the_child_exits_once_its_parent_is_killed():
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT, CHILD], stdout=subprocess.PIPE, text=True
    )
    child = None
    try:
        child = psutil.Process(int(parent.stdout.readline()))
        time.sleep(1.0)  # the watchdog is up, the parent alive: the child stays
        assert child.is_running() and child.status() != psutil.STATUS_ZOMBIE
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait(10)
        deadline = time.monotonic() + 10
        while _alive(child) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(child), "the orphaned child is still running"
    finally:
        parent.kill()
        if child is not None and _alive(child):
            child.kill()


def _alive(process: psutil.Process) -> bool:
    try:
        return process.is_running() and process.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False
