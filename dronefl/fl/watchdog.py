"""A ClientApp's process ends when the process that started it is gone.

A ClientApp runs in a Ray worker (the simulation engine: a child of Ray's raylet) or in a
``flwr-clientapp`` process (the Deployment Engine: a child of the SuperNode's executor). When a
run is killed, Ray's workers normally exit within a second with their raylet; but in 3 of 10
test-suite runs on a loaded 2-core machine one ``ray::ClientAppActor`` of a killed closed-loop
episode outlived its raylet and the rest of the run by over 150 s (why is not known). The
watchdog turns "the parent is gone" into an exit, whatever the worker was doing.
"""

from __future__ import annotations

import os
import threading
import time

_started = threading.Lock()
_running = False


def exit_with_parent(poll_s: float = 1.0) -> None:
    """Start, once per process, a daemon thread that ends this process (``os._exit(1)``, no
    clean-up: there is nobody left to report to) within ``poll_s`` s of its parent's death,
    seen as a change of ``os.getppid()`` (an orphan is re-parented to ``init`` or a
    sub-reaper)."""
    global _running
    with _started:
        if _running:
            return
        _running = True
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()
