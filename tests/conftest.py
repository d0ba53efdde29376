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
from dataclasses import replace
from pathlib import Path

import psutil
import pytest
from cli_child import run_dronefl
from filelock import FileLock

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


#: The training presets whose quick models :func:`quick_pretrained` caches: the default and
#: the recommended one (``make demo``'s), whose model reads box sizes otherwise.
QUICK_PRESETS = ("ours", "metric-scaffold")


def quick_gaps() -> tuple[float, ...]:
    """The pretraining detection gaps the quick models stand in for: every candidate of
    ``--pretrain-gaps auto`` (0 is the ``ours`` and ``paper`` settings')."""
    from dronefl.experiments.gap_choice import GAP_CANDIDATES

    return GAP_CANDIDATES


def stand_in_gap_choice(spec, folder: Path) -> None:
    """Record ``--pretrain-gaps auto``'s choice for ``spec`` in ``folder`` as 0 (the quick
    models are one model for every candidate; no validation flight is flown for them)."""
    from dronefl.experiments.gap_choice import GapChoice

    GapChoice(0.0, {}).save(GapChoice.path(spec, folder, quick_gaps()))


@pytest.fixture(scope="session")
def quick_pretrained(tmp_path_factory):
    """DroneFL models for Case 1, one per preset of :data:`QUICK_PRESETS`, each trained for
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
            _train_quick_model(folder)
            (folder / "ready").touch()
    return folder


@pytest.fixture
def quick_pretrained_case2(quick_pretrained, tmp_path) -> Path:
    """``quick_pretrained``'s models as Case 2's pretrained DroneFL models (a model is the same
    for any scenario), in ``tmp_path / "pretrained"``."""
    from dronefl.config import load_scenario
    from dronefl.experiments.pretrain import PretrainSpec
    from dronefl.fl.checkpoint import Checkpoint, load_checkpoint, save_checkpoint

    for preset in QUICK_PRESETS:
        for gaps in quick_gaps():
            case1, case2 = (
                PretrainSpec(
                    load_scenario(name), "dronefl", preset=preset, detection_gaps=gaps
                ).settings(folder)
                for name, folder in (
                    ("case1", quick_pretrained),
                    ("case2", tmp_path / "pretrained"),
                )
            )
            state = load_checkpoint(case1.checkpoint_path, case1.history_path, "dronefl").state
            checkpoint = Checkpoint("dronefl", 20, state, [])
            save_checkpoint(case2.checkpoint_path, case2.history_path, checkpoint)
        stand_in_gap_choice(
            PretrainSpec(load_scenario("case2"), "dronefl", preset=preset), tmp_path / "pretrained"
        )
    return tmp_path / "pretrained"


def _train_quick_model(folder: Path) -> None:
    import torch

    from dronefl.config import load_scenario
    from dronefl.experiments.pretrain import PretrainSpec
    from dronefl.experiments.simulate import simulate
    from dronefl.fl.checkpoint import Checkpoint, save_checkpoint
    from dronefl.logs import load_run
    from dronefl.models.model import build_model
    from dronefl.models.train import TrainConfig, train_local
    from dronefl.models.windows import WindowSet, WindowSpec, build_windows, ground_truth_labels

    if folder.exists():  # a run that died while building it
        shutil.rmtree(folder)
    data = folder / "data"
    simulate(
        load_scenario("case1"),
        environment="crop_field",
        duration=120.0,
        seed=5,
        out=data,
        progress=False,
        plot=False,
    )
    logs, truth = load_run(data)
    spec = WindowSpec(10, 1, relative=True, stride=2)
    windows = WindowSet.concat(
        [build_windows(log, ground_truth_labels(log, truth), spec) for log in logs.values()]
    )
    torch.set_num_threads(1)
    for preset in QUICK_PRESETS:
        spec = PretrainSpec(load_scenario("case1"), "dronefl", preset=preset)
        model = build_model(spec.model, seed=0)
        train_local(model, windows, TrainConfig(epochs=20, batch_size=32, seed=0))
        for gaps in quick_gaps():  # one stand-in for the pretrainings with and without gaps
            settings = replace(spec, detection_gaps=gaps).settings(folder)
            save_checkpoint(
                settings.checkpoint_path,
                settings.history_path,
                Checkpoint("dronefl", settings.rounds, model.state_dict(), []),
            )
        stand_in_gap_choice(spec, folder)


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
