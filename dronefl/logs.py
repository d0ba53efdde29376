"""Recorded run files: each drone's onboard log and the simulator's ground truth (format v1).

A recorded run folder holds::

    drone_<id>.npz      one per drone: what the drone stores on board (never images)
    ground_truth.npz    every target's and drone's true trajectory (for labels and metrics)
    summary.json        run statistics (see ``dronefl.experiments.simulate``)

``drone_<id>.npz`` (``format = "dronefl.onboard_log"``, ``version = 1``), ``T`` steps, ``N``
targets of the scenario (all of them, assigned or not, in scenario order):

============== =========== ======= =====================================================
key            shape       dtype   meaning
============== =========== ======= =====================================================
t              (T,)        float64 time, s
odometry       (T, 12)     float32 noisy odometry, layout ``dronefl.types.ODOMETRY_FIELDS``
target_ids     (N,)        int32   target id of each column
assigned       (N,)        bool    target is in this drone's assignment N_i
boxes          (T, N, 4)   float32 normalised (cx, cy, w, h); NaN where not detected
detected       (T, N)      bool    detection mask
confidence     (T, N)      float32 detector confidence; 0 where not detected
meta           ()          str     JSON: scenario, environment, seed, drone_id, altitude (m),
                                   rate_hz, detector, camera
============== =========== ======= =====================================================

``ground_truth.npz`` (``format = "dronefl.ground_truth"``, ``version = 1``):
``t`` (T,), ``target_ids`` (N,), ``target_position`` (T, N, 2) m, ``target_velocity``
(T, N, 2) m/s, ``target_heading`` (T, N) rad, ``drone_ids`` (M,), ``drone_position``
(T, M, 2) m, ``drone_velocity`` (T, M, 2) m/s, ``drone_altitude`` (M,) m, ``meta``.

Loading checks format, version, keys, shapes and finiteness and raises :class:`LogError`
naming the file for anything truncated or corrupt.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dronefl.io import atomic_savez

ONBOARD_FORMAT = "dronefl.onboard_log"
GROUND_TRUTH_FORMAT = "dronefl.ground_truth"
FORMAT_VERSION = 1


class LogError(ValueError):
    """A recorded log file is missing, truncated, corrupt or of an unknown format."""


@dataclass(frozen=True)
class OnboardLog:
    """One drone's onboard record of a run (see the module docstring for the layout)."""

    drone_id: int
    altitude: float
    t: np.ndarray
    odometry: np.ndarray
    target_ids: np.ndarray
    assigned: np.ndarray
    boxes: np.ndarray
    detected: np.ndarray
    confidence: np.ndarray
    meta: dict[str, Any]

    @property
    def assigned_ids(self) -> tuple[int, ...]:
        """Ids of the targets this drone watches, in scenario order."""
        return tuple(int(i) for i in self.target_ids[self.assigned])

    def column(self, target_id: int) -> int:
        """Column index of ``target_id`` in ``boxes``/``detected``."""
        hits = np.flatnonzero(self.target_ids == target_id)
        if hits.size == 0:
            raise KeyError(f"target {target_id} is not in drone {self.drone_id}'s log")
        return int(hits[0])

    def save(self, path: str | Path) -> Path:
        """Write the log atomically to ``path``."""
        return atomic_savez(
            path,
            format=np.array(ONBOARD_FORMAT),
            version=np.array(FORMAT_VERSION),
            t=self.t.astype(np.float64),
            odometry=self.odometry.astype(np.float32),
            target_ids=self.target_ids.astype(np.int32),
            assigned=self.assigned.astype(bool),
            boxes=self.boxes.astype(np.float32),
            detected=self.detected.astype(bool),
            confidence=self.confidence.astype(np.float32),
            meta=np.array(
                json.dumps({**self.meta, "drone_id": self.drone_id, "altitude": self.altitude})
            ),
        )

    @classmethod
    def load(cls, path: str | Path) -> OnboardLog:
        """Read and validate a log written by :meth:`save`."""
        data = _read_npz(Path(path), ONBOARD_FORMAT, _ONBOARD_KEYS)
        n_steps = data["t"].shape[0]
        n_targets = data["target_ids"].shape[0]
        _expect_shape(path, data, "odometry", (n_steps, 12))
        _expect_shape(path, data, "assigned", (n_targets,))
        _expect_shape(path, data, "boxes", (n_steps, n_targets, 4))
        _expect_shape(path, data, "detected", (n_steps, n_targets))
        _expect_shape(path, data, "confidence", (n_steps, n_targets))
        _expect_finite(path, data, ("t", "odometry", "confidence"))
        if not np.isfinite(data["boxes"][data["detected"]]).all():
            raise LogError(f"{path}: boxes of detected targets hold NaN or inf values")
        meta = data["meta"]
        return cls(
            drone_id=int(meta["drone_id"]),
            altitude=float(meta["altitude"]),
            t=data["t"],
            odometry=data["odometry"],
            target_ids=data["target_ids"],
            assigned=data["assigned"].astype(bool),
            boxes=data["boxes"],
            detected=data["detected"].astype(bool),
            confidence=data["confidence"],
            meta=meta,
        )


@dataclass(frozen=True)
class GroundTruth:
    """The simulator's true trajectories of every target and drone in a run."""

    t: np.ndarray
    target_ids: np.ndarray
    target_position: np.ndarray
    target_velocity: np.ndarray
    target_heading: np.ndarray
    drone_ids: np.ndarray
    drone_position: np.ndarray
    drone_velocity: np.ndarray
    drone_altitude: np.ndarray
    meta: dict[str, Any]

    def target_column(self, target_id: int) -> int:
        """Column of ``target_id`` in the ``target_*`` arrays."""
        hits = np.flatnonzero(self.target_ids == target_id)
        if hits.size == 0:
            raise KeyError(f"target {target_id} is not in the ground truth")
        return int(hits[0])

    def save(self, path: str | Path) -> Path:
        """Write the ground truth atomically to ``path``."""
        return atomic_savez(
            path,
            format=np.array(GROUND_TRUTH_FORMAT),
            version=np.array(FORMAT_VERSION),
            t=self.t.astype(np.float64),
            target_ids=self.target_ids.astype(np.int32),
            target_position=self.target_position.astype(np.float64),
            target_velocity=self.target_velocity.astype(np.float64),
            target_heading=self.target_heading.astype(np.float64),
            drone_ids=self.drone_ids.astype(np.int32),
            drone_position=self.drone_position.astype(np.float64),
            drone_velocity=self.drone_velocity.astype(np.float64),
            drone_altitude=self.drone_altitude.astype(np.float64),
            meta=np.array(json.dumps(self.meta)),
        )

    @classmethod
    def load(cls, path: str | Path) -> GroundTruth:
        """Read and validate a file written by :meth:`save`."""
        data = _read_npz(Path(path), GROUND_TRUTH_FORMAT, _TRUTH_KEYS)
        n_steps = data["t"].shape[0]
        n_targets = data["target_ids"].shape[0]
        n_drones = data["drone_ids"].shape[0]
        _expect_shape(path, data, "target_position", (n_steps, n_targets, 2))
        _expect_shape(path, data, "target_velocity", (n_steps, n_targets, 2))
        _expect_shape(path, data, "target_heading", (n_steps, n_targets))
        _expect_shape(path, data, "drone_position", (n_steps, n_drones, 2))
        _expect_shape(path, data, "drone_velocity", (n_steps, n_drones, 2))
        _expect_shape(path, data, "drone_altitude", (n_drones,))
        _expect_finite(path, data, tuple(k for k in _TRUTH_KEYS if k != "meta"))
        return cls(**{k: data[k] for k in _TRUTH_KEYS})


_ONBOARD_KEYS = (
    "t",
    "odometry",
    "target_ids",
    "assigned",
    "boxes",
    "detected",
    "confidence",
    "meta",
)
_TRUTH_KEYS = (
    "t",
    "target_ids",
    "target_position",
    "target_velocity",
    "target_heading",
    "drone_ids",
    "drone_position",
    "drone_velocity",
    "drone_altitude",
    "meta",
)


def _read_npz(path: Path, expected_format: str, keys: tuple[str, ...]) -> dict[str, Any]:
    if not path.is_file():
        raise LogError(f"{path}: no such log file")
    try:
        with np.load(path, allow_pickle=False) as npz:
            fmt = str(npz["format"]) if "format" in npz.files else None
            if fmt != expected_format:
                raise LogError(f"{path}: not a {expected_format} file (format {fmt!r})")
            version = int(npz["version"])
            if version != FORMAT_VERSION:
                raise LogError(
                    f"{path}: format version {version}; this DroneFL reads version {FORMAT_VERSION}"
                )
            missing = [k for k in keys if k not in npz.files]
            if missing:
                raise LogError(f"{path}: missing arrays {missing}")
            data = {k: npz[k] for k in keys}
    except LogError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError) as exc:
        raise LogError(f"{path}: truncated or corrupt log file ({type(exc).__name__})") from None
    try:
        data["meta"] = json.loads(str(data["meta"]))
    except json.JSONDecodeError:
        raise LogError(f"{path}: corrupt metadata") from None
    if data["t"].ndim != 1:
        raise LogError(f"{path}: 't' must be one-dimensional")
    return data


def _expect_shape(path: str | Path, data: dict, key: str, shape: tuple[int, ...]) -> None:
    if data[key].shape != shape:
        raise LogError(f"{path}: '{key}' has shape {data[key].shape}, expected {shape}")


def _expect_finite(path: str | Path, data: dict, keys: tuple[str, ...]) -> None:
    for key in keys:
        arr = data[key]
        if np.issubdtype(arr.dtype, np.floating) and not np.isfinite(arr).all():
            raise LogError(f"{path}: '{key}' holds NaN or inf values")


def load_run(folder: str | Path) -> tuple[dict[int, OnboardLog], GroundTruth]:
    """Load every ``drone_<id>.npz`` and ``ground_truth.npz`` of a recorded run folder."""
    folder = Path(folder)
    if not folder.is_dir():
        raise LogError(f"{folder}: no such run folder")
    paths = sorted(folder.glob("drone_*.npz"))
    if not paths:
        raise LogError(f"{folder}: no drone_<id>.npz logs in this folder")
    logs = {log.drone_id: log for log in map(OnboardLog.load, paths)}
    return logs, GroundTruth.load(folder / "ground_truth.npz")


PSEUDO_LABEL_FORMAT = "dronefl.pseudo_labels"


@dataclass(frozen=True)
class PseudoLabels:
    """Target positions that stand in for ground truth when training in the field: the cloud's
    fused EKF tracks (``position`` ``(T, N, 2)`` m on the drones' time grid ``t`` ``(T,)``, NaN
    where no track existed), saved beside the onboard logs of an FL round: ``tracks_<id>.npz``,
    drone ``id``'s own, in the closed loop's round folders; ``tracks.npz`` on a deployed
    drone's disk."""

    t: np.ndarray
    target_ids: np.ndarray
    position: np.ndarray

    def save(self, path: str | Path) -> Path:
        """Write the labels atomically to ``path``."""
        return atomic_savez(
            path,
            format=np.array(PSEUDO_LABEL_FORMAT),
            version=np.array(FORMAT_VERSION),
            t=self.t.astype(np.float64),
            target_ids=self.target_ids.astype(np.int32),
            position=self.position.astype(np.float64),
            meta=np.array("{}"),
        )

    @classmethod
    def load(cls, path: str | Path) -> PseudoLabels:
        """Read and validate a file written by :meth:`save`."""
        data = _read_npz(Path(path), PSEUDO_LABEL_FORMAT, ("t", "target_ids", "position", "meta"))
        _expect_shape(path, data, "position", (data["t"].shape[0], data["target_ids"].shape[0], 2))
        _expect_finite(path, data, ("t",))  # positions are NaN where no track existed
        return cls(data["t"], data["target_ids"], data["position"])

    def for_log(self, log: OnboardLog) -> np.ndarray:
        """Labels ``(T, N, 2)`` in ``log``'s column order (NaN for targets without labels)."""
        if self.t.shape != log.t.shape or not np.allclose(self.t, log.t, atol=1e-6):
            raise LogError(f"drone {log.drone_id}: pseudo-labels are on another time grid")
        out = np.full((len(log.t), len(log.target_ids), 2), np.nan)
        for j, target_id in enumerate(log.target_ids):
            hits = np.flatnonzero(self.target_ids == target_id)
            if hits.size:
                out[:, j] = self.position[:, hits[0]]
        return out
