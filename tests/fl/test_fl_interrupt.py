"""Ctrl-C (SIGTERM) in the middle of a federated run ends `dronefl` promptly with exit code 130
(143) and one line, every process it started exits, and `--resume` can go on from what was
written.

Flower's simulation engine, interrupted, stops Ray but leaves its worker threads blocked in
``ray.get``; before ``dronefl.cli.leave`` the process then waited for them forever."""

import json
import os
import signal
import subprocess
import sys
import time
from types import SimpleNamespace

import psutil
import pytest
import ray
from flwr.server.superlink.fleet.vce.backend.raybackend import RayBackend

from dronefl.fl.checkpoint import load_checkpoint
from dronefl.fl.simulation import ENGINE_INTERRUPTED, _interruptible_backend

TINY = [
    "--scenario",
    "case1",
    "--duration",
    "40",
    "--stride",
    "5",
    "--seeds",
    "3",
    "--set",
    "training.epochs=2",
]
#: Seconds the interrupted process may take to end (the grace for stuck threads is 5 s).
EXIT_WITHIN_S = 30.0
#: ``dronefl ARGV`` with Python's Ctrl-C handler installed: a process started with SIGINT
#: ignored (as POSIX shells start background jobs, so also a test run started as one) keeps
#: ignoring it, and this test would then see the run finish all its rounds (exit code 0).
_WITH_CTRL_C = (
    "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "from dronefl.cli import main; sys.argv[0] = 'dronefl'; main()"
)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("signum", "code", "said"),
    [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated (SIGTERM)")],
)
def test_a_signal_during_a_round_ends_the_run_and_every_process(tmp_path, signum, code, said):
    out = tmp_path / "fl"
    env = {**os.environ, "FLWR_TELEMETRY_ENABLED": "0", "MPLBACKEND": "Agg"}
    argv = ["fl-offline", *TINY, "--rounds", "40", "--methods", "dronefl", "--out", str(out)]
    process = subprocess.Popen(
        [sys.executable, "-c", _WITH_CTRL_C, *argv],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    history = out / "seed_3" / "dronefl" / "history.json"
    started: dict[int, psutil.Process] = {}
    deadline = time.monotonic() + 240
    try:
        while not history.is_file() and process.poll() is None:
            assert time.monotonic() < deadline, "no round finished within 240 s"
            for child in psutil.Process(process.pid).children(recursive=True):
                started.setdefault(child.pid, child)
            time.sleep(0.2)
        assert process.poll() is None, "the run ended before it could be interrupted"
        time.sleep(1.0)  # into the next round
        interrupted = time.monotonic()
        process.send_signal(signum)
        try:
            _, err = process.communicate(timeout=EXIT_WITHIN_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"dronefl still running {EXIT_WITHIN_S:.0f} s after {signum.name}")
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == code, err[-3000:]
    assert f"{said}: finished rounds and episodes are kept" in err
    assert "Traceback" not in err
    assert time.monotonic() - interrupted < EXIT_WITHIN_S
    # Every process of the run (Ray's included) is gone within 30 s.
    gone_by = time.monotonic() + 30
    while (alive := [p for p in started.values() if _alive(p)]) and time.monotonic() < gone_by:
        time.sleep(0.5)
    assert not alive, f"left running after {signum.name}: {[p.name() for p in alive]}"
    # What was written is whole: the checkpoint and the history of the finished rounds.
    checkpoint = load_checkpoint(history.parent / "checkpoint.npz", history, "dronefl")
    assert checkpoint.server_round >= 1
    assert len(json.loads(history.read_text())) >= checkpoint.server_round


def _alive(process: psutil.Process) -> bool:
    """Running and not a zombie (an exited process that its new parent has not reaped yet)."""
    try:
        return process.is_running() and process.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def test_the_engine_kills_busy_actors_too_and_after_ctrl_c_leaves_ray_up(monkeypatch):
    """Flower's ``RayBackend.terminate`` asks the idle actors to stop (each logs a warning) and
    shuts Ray down while busy ones still have worker threads waiting on them; ours kills both
    kinds, and after Ctrl-C leaves the shutdown to ``dronefl.cli.leave``, once the threads
    have ended."""
    calls: list[str] = []
    monkeypatch.setattr(ray, "kill", lambda actor, no_restart: calls.append(f"kill {actor}"))
    monkeypatch.setattr(ray, "shutdown", lambda: calls.append("shutdown"))
    pool = SimpleNamespace(pool=["idle"], _future_to_actor={"job": "busy"})
    backend = SimpleNamespace(pool=pool)
    stock = RayBackend.terminate

    with _interruptible_backend():
        RayBackend.terminate(backend)  # type: ignore[arg-type]
        assert calls == ["kill idle", "kill busy", "shutdown"]
        calls.clear()
        ENGINE_INTERRUPTED.set()
        try:
            RayBackend.terminate(backend)  # type: ignore[arg-type]
        finally:
            ENGINE_INTERRUPTED.clear()
        assert calls == ["kill idle", "kill busy"]
    assert RayBackend.terminate is stock
