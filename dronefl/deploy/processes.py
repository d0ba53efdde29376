"""Owned child processes: whoever starts one stops it, on success, failure and Ctrl-C alike.

:class:`Children` starts each child in its own process group (``start_new_session``) with
its output in a log file, and on exit stops every group: SIGTERM, a grace period, SIGKILL.
Flower detaches some of its helpers into new sessions (the SuperLink's SuperExec), so every
child also inherits a marker :data:`OWNER_ENV` naming this launcher; :func:`marked` finds
every process that carries it, wherever it was reparented, and :meth:`Children.stop` ends
those too. Nothing else on the machine is touched.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import threading
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import psutil

#: Environment variable marking every process started by one launcher (value: its id).
OWNER_ENV = "DRONEFL_DEPLOY_OWNER"


class DeployError(RuntimeError):
    """A deployment step failed; the message is one line saying what and where."""


def port_in_use(host: str, port: int) -> bool:
    """Whether ``host:port`` cannot be bound (another process listens there; connections of
    a finished process lingering in TIME_WAIT do not count, as for any server)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError:
            return True
    return False


def port_open(host: str, port: int, timeout: float = 0.2) -> bool:
    """Whether something accepts TCP connections on ``host:port``."""
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def marked(owner: str) -> list[psutil.Process]:
    """Every live process whose environment carries ``OWNER_ENV=owner``."""
    found = []
    for process in psutil.process_iter():
        with contextlib.suppress(psutil.Error):
            if process.environ().get(OWNER_ENV) == owner and process.status() != "zombie":
                found.append(process)
    return found


def _descendants(pid: int) -> list[psutil.Process]:
    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.Error:
        return []


def stop_processes(processes: Sequence[psutil.Process], grace: float) -> None:
    """SIGTERM ``processes``, wait up to ``grace`` s, SIGKILL what is left."""
    for process in processes:
        with contextlib.suppress(psutil.Error):
            process.terminate()
    _, left = psutil.wait_procs(processes, timeout=grace)
    for process in left:
        with contextlib.suppress(psutil.Error):
            process.kill()
    psutil.wait_procs(left, timeout=grace)


@dataclass
class Child:
    """One started child: its ``name``, process and log file (its output starts at byte
    ``offset``: a restarted child appends to the log of its predecessor)."""

    name: str
    process: subprocess.Popen
    log: Path
    offset: int = 0

    def output(self) -> str:
        """What this child has written to its log so far."""
        try:
            with self.log.open("rb") as handle:
                handle.seek(self.offset)
                return handle.read().decode(errors="replace")
        except OSError:
            return ""

    def last_line(self) -> str:
        """The last non-empty line of its output (what a failed child said last)."""
        lines = [ln.strip() for ln in self.output().splitlines() if ln.strip()]
        return lines[-1] if lines else ""


@dataclass
class Children:
    """The children of one process, stopped together when the ``with`` block exits.

    The top-level launcher (no :data:`OWNER_ENV` in its environment) starts each child in a
    new process group and marks them with a fresh owner id; a process that is itself such a
    child (a drone starting its SuperNode) keeps its children in its own group, so that
    stopping (or killing) its group stops them too, and passes its owner id on.
    """

    logs: Path
    grace: float = 5.0
    started: list[Child] = field(default_factory=list)
    _files: list[IO[bytes]] = field(default_factory=list)

    def __post_init__(self) -> None:
        inherited = os.environ.get(OWNER_ENV)
        self.top_level = inherited is None
        self.owner = inherited or uuid.uuid4().hex

    def __enter__(self) -> Children:
        self.logs.mkdir(parents=True, exist_ok=True)
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self, name: str, command: Sequence[str], env: dict[str, str] | None = None) -> Child:
        """Start ``command`` as ``name``, output to ``<logs>/<name>.log``."""
        log = self.logs / f"{name}.log"
        offset = log.stat().st_size if log.is_file() else 0
        handle = log.open("ab")
        self._files.append(handle)
        environment = {**os.environ, **(env or {}), OWNER_ENV: self.owner}
        process = subprocess.Popen(
            list(command),
            stdout=handle,
            stderr=subprocess.STDOUT,
            stdin=subprocess.DEVNULL,
            env=environment,
            start_new_session=self.top_level,
        )
        child = Child(name, process, log, offset)
        self.started.append(child)
        return child

    def failed(self) -> Child | None:
        """A child that has exited with a non-zero code, if any."""
        for child in self.started:
            code = child.process.poll()
            if code is not None and code != 0:
                return child
        return None

    def kill(self, child: Child, sig: int) -> None:
        """Send ``sig`` to ``child``: to its whole process group when it leads one."""
        with contextlib.suppress(ProcessLookupError, PermissionError):
            if self.top_level:
                os.killpg(child.process.pid, sig)
            else:
                child.process.send_signal(sig)

    def stop_child(self, child: Child) -> None:
        """Stop ``child`` (SIGTERM, then SIGKILL after the grace period) and its helpers."""
        helpers = _descendants(child.process.pid)
        if child.process.poll() is None:
            self.kill(child, signal.SIGTERM)
            try:
                child.process.wait(self.grace)
            except subprocess.TimeoutExpired:
                self.kill(child, signal.SIGKILL)
                child.process.wait()
        elif self.top_level:  # its leader is gone; members of its group may not be
            self.kill(child, signal.SIGKILL)
        stop_processes([p for p in helpers if p.is_running()], self.grace)

    def stop(self) -> None:
        """Stop every child (last started first); the launcher then also every process still
        carrying its marker. A second Ctrl-C or SIGTERM waits until this is done (it would
        otherwise abort the clean-up half way)."""
        signals = {signal.SIGINT, signal.SIGTERM}
        blocked = threading.current_thread() is threading.main_thread()
        if blocked:
            signal.pthread_sigmask(signal.SIG_BLOCK, signals)
        try:
            for child in reversed(self.started):
                self.stop_child(child)
            if self.top_level:
                stop_processes(marked(self.owner), self.grace)
        finally:
            if blocked:
                signal.pthread_sigmask(signal.SIG_UNBLOCK, signals)
        for handle in self._files:
            handle.close()
        self._files.clear()


def wait_for(condition, timeout: float, what: str, children: Children | None = None) -> None:
    """Poll ``condition()`` until true; raise :class:`DeployError` after ``timeout`` s or as
    soon as one of ``children`` fails (naming it and its last log line)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if children is not None and (child := children.failed()) is not None:
            raise DeployError(
                f"{child.name} exited with code {child.process.returncode} while waiting for "
                f"{what}: {child.last_line()} (log: {child.log})"
            )
        if time.monotonic() > deadline:
            raise DeployError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.1)
