"""Test-wide settings: headless plotting, tool caches inside a temp dir, no telemetry."""

import os
import tempfile

_CACHE = tempfile.mkdtemp(prefix="dronefl-test-cache-")
os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("MPLCONFIGDIR", os.path.join(_CACHE, "matplotlib"))
os.environ.setdefault("FLWR_HOME", os.path.join(_CACHE, "flwr"))
os.environ.setdefault("FLWR_TELEMETRY_ENABLED", "0")
os.environ.setdefault("YOLO_OFFLINE", "1")
os.environ.setdefault("YOLO_CONFIG_DIR", os.path.join(_CACHE, "ultralytics"))
os.environ.setdefault("RAY_DEDUP_LOGS", "0")
