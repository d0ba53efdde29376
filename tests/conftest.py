"""Test-wide settings (headless plotting, tool caches inside a temp dir, no telemetry, one Ray
worker per simulation engine), the shared fixture of a quickly pretrained Case 1 model, and
``cli_process``, which runs the ``dronefl`` command in child processes and checks that every
process they started is gone at the end (the kill/resume tests)."""

import atexit
import contextlib
import ctypes
import multiprocessing
import os
import shutil
import signal
import tempfile
import time
from pathlib import Path

import psutil
import pytest
from cli_child import run_dronefl
from filelock import FileLock
from quick_models import plant_quick_models, train_quick_models

_CACHE = tempfile.mkdtemp(prefix="dronefl-test-cache-")
atexit.register(shutil.rmtree, _CACHE, ignore_errors=True)  # each pytest process its own
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("MPLCONFIGDIR", os.path.join(_CACHE, "matplotlib"))
os.environ.setdefault("FLWR_HOME", os.path.join(_CACHE, "flwr"))
os.environ.setdefault("FLWR_TELEMETRY_ENABLED", "0")
os.environ.setdefault("YOLO_OFFLINE", "1")
os.environ.setdefault("YOLO_CONFIG_DIR", os.path.join(_CACHE, "ultralytics"))
os.environ.setdefault("RAY_DEDUP_LOGS", "0")
# One Ray worker per simulation engine: the tests already run in parallel (make test: -n auto),
# and a second worker costs ~5 CPU-s per engine start (see dronefl.fl.simulation.sim_workers).
os.environ.setdefault("DRONEFL_SIM_WORKERS", "1")


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: one worker more than the cores. The slow tests wait part of their time on
    process start-ups and Ray's start and teardown, so one worker per core leaves the CPU idle
    (measured on 2 cores: 86 % busy with 2 workers, 319 s; 94 % with 3, 298 s)."""
    return (os.cpu_count() or 1) + 1


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Files with a ``slow`` test run first (in collection order, then the rest): with
    ``make test``'s ``-n auto --dist loadfile --no-loadscope-reorder`` their process start-ups
    and Ray's teardown waits overlap the many quick tests instead of ending the run."""
    slow = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow)


@pytest.fixture(scope="session")
def quick_pretrained(tmp_path_factory):
    """DroneFL models for Case 1, one per setting of :data:`QUICK_SETTINGS`, each trained for
    ~6 s on 120 s of crop field (held-out error ~2.5 m^2, good enough for the closed loop to
    keep its targets in view), cached where the closed loop and ``deploy up --pretrained`` look
    for pretrained weights. Built once per
    run: the first pytest-xdist worker to ask builds it, under a file lock in the folder the
    workers share; the others wait for it and reuse it (it is only read)."""
    base = tmp_path_factory.getbasetemp()
    if "PYTEST_XDIST_WORKER" in os.environ:
        base = base.parent
    folder = base / "quick-pretrained"
    with FileLock(f"{folder}.lock"):
        if not (folder / "ready").is_file():
            train_quick_models(folder)
            (folder / "ready").touch()
    return folder


@pytest.fixture
def quick_pretrained_case2(quick_pretrained, tmp_path) -> Path:
    """``quick_pretrained``'s models as Case 2's pretrained DroneFL models (a model is the same
    for any scenario), in ``tmp_path / "pretrained"``."""
    return plant_quick_models(quick_pretrained, "case2", tmp_path / "pretrained")


PR_SET_CHILD_SUBREAPER = 36
#: Children are forked from a server that has imported the CLI once (a fresh interpreter per
#: run would spend most of the test importing torch; Adam imports torch._dynamo on first use).
_SERVER = multiprocessing.get_context("forkserver")
_SERVER.set_forkserver_preload(
    ["dronefl.cli", "dronefl.experiments.fl_offline", "dronefl.experiments.track", "torch._dynamo"]
)


def _adopt_orphans() -> None:
    """Make this process the reaper of its descendants' orphans (Linux ``prctl``). A killed run's
    Ray processes are orphaned; where PID 1 never reaps (as in some containers) the dead raylet
    would stay a zombie, which Ray's agents take for a live parent, and never exit."""
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0)


def _running(process: psutil.Process) -> bool:
    """Alive (a zombie that was our orphan is reaped here; any other zombie counts as gone)."""
    try:
        if process.status() == psutil.STATUS_ZOMBIE:
            with contextlib.suppress(ChildProcessError):
                os.waitpid(process.pid, os.WNOHANG)
            return False
        return process.is_running()
    except psutil.NoSuchProcess:
        return False


#: Seconds a killed run's processes get to exit by themselves, counted from the end of the
#: test that started them. Ray's agents wait ``RAY_gcs_rpc_server_reconnect_timeout_s`` (20 s,
#: set by :mod:`dronefl.fl.simulation`) for the dead GCS, but in 2 of 8 suite runs on a loaded
#: machine a Ray worker of a killed episode lived over 90 s after the kill (cause not found).
KILLED_GRACE = 150.0


@pytest.fixture(scope="session")
def _orphans():
    """Processes that ``cli_process``'s killed runs left behind, with the test that started
    them and the time by which they must be gone; checked when the session (or xdist worker)
    ends, so that the wait overlaps the tests that come after."""
    watched: list[tuple[str, float, list[psutil.Process]]] = []
    yield watched
    left = []
    for test, deadline, processes in watched:
        while (alive := [p for p in processes if _running(p)]) and time.monotonic() < deadline:
            time.sleep(0.5)
        for p in alive:  # clean up before failing
            with contextlib.suppress(psutil.Error):
                left.append(f"{p.name()} (pid {p.pid}, started by {test})")
                p.kill()
    assert not left, f"left running {KILLED_GRACE:.0f} s after their test: {left}"


@pytest.fixture
def cli_process(request, _orphans):
    """``cli_process(argv, crash_at=None)`` runs ``dronefl ARGV`` in a child process, with
    ``DRONEFL_CRASH_AT=crash_at`` when given (:mod:`dronefl.io`), and returns its exit code (0,
    or ``-SIGKILL`` for a run that killed itself). Every process a run started (Ray's
    included) must exit by itself: within 30 s of a normal end (checked here); a killed run's
    within :data:`KILLED_GRACE` s of the test's end (checked at the end of the session,
    ``_orphans``).

    After a SIGKILL, Ray's raylet, GCS and workers go within seconds; its dashboard and
    runtime-env agents first try to tell the dead GCS, for 20 s. The test goes on meanwhile."""
    killed: list[psutil.Process] = []

    def run(argv: list[str], crash_at: str | None = None) -> int:
        _adopt_orphans()
        child = _SERVER.Process(target=run_dronefl, args=(argv, crash_at))
        child.start()
        mine: dict[int, psutil.Process] = {}
        while child.exitcode is None:
            try:
                for p in psutil.Process(child.pid).children(recursive=True):
                    mine.setdefault(p.pid, p)
            except psutil.NoSuchProcess:
                pass
            time.sleep(0.2)
        child.join()
        assert child.exitcode in (0, -signal.SIGKILL), f"{argv[0]} exited {child.exitcode}"
        if child.exitcode != 0:
            killed.extend(mine.values())
            return child.exitcode
        deadline = time.monotonic() + 30  # a run that ended normally leaves nothing behind
        while (alive := [p for p in mine.values() if _running(p)]) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not alive, f"left running by {argv[0]}: {[p.name() for p in alive]}"
        return child.exitcode

    yield run
    _orphans.append((request.node.nodeid, time.monotonic() + KILLED_GRACE, killed))
