"""Fixtures of the deployment tests."""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import pytest
from deploy_helpers import MARK, ROOT


@pytest.fixture
def run_env(tmp_path: Path) -> dict[str, str]:
    """Environment for a deployment command: this checkout first, caches in ``tmp_path``,
    and a fresh :data:`MARK`."""
    env = dict(os.environ)
    env.pop("DRONEFL_DEPLOY_OWNER", None)
    env.update(
        {
            "PYTHONPATH": str(ROOT),
            MARK: uuid.uuid4().hex,
            "FLWR_TELEMETRY_ENABLED": "0",
            "MPLBACKEND": "Agg",
            "YOLO_OFFLINE": "1",
            "HOME": str(tmp_path / "home"),
        }
    )
    return env
