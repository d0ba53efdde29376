"""Training windows for the trajectory predictor, built from one drone's onboard log.

A window is one (drone i, assigned target j, time index t): the last ``L_p`` steps
``t-L_p+1 .. t`` of ``[box (4), odometry (12), detected (1)]`` as inputs and the target's
positions at ``t+1 .. t+L_f`` as labels. Windows in which j was never detected are dropped.

Feature scaling uses fixed constants (below), the same on every drone, so no statistic of one
drone's data leaks to another and a model trained anywhere reads inputs the same way:

============ =================================================== =========================
feature      value                                               typical range
============ =================================================== =========================
box          ``2 (cx - 0.5)``, ``2 (cy - 0.5)``, ``w * 10``,     [-1, 1], [0, 2]
             ``h * 10``; all four zero where j was missed
x, y         ``(x - x_t) / 10 m`` (relative) or                 a few units /
             ``(x - W/2) / (W/2)``, ``(y - H/2) / (W/2)`` (absolute,  [-1, 1]
             W x H m the scenario's field)
z            ``z / 50 m``                                        [0.4, 1.2]
vx, vy, vz   ``v / 3 m/s``                                       [-1, 1]
attitude     roll, pitch, yaw in rad, rates in rad/s, unscaled   small
detected     1 where j was detected at that step, else 0         {0, 1}
============ =================================================== =========================

Labels are positions in m, minus ``origin``: the drone's odometry (x, y) at time t when
``relative`` (what the drone knows of itself), else the centre of the scenario's field
(absolute positions, centred so that the baselines' outputs start in a sensible range). A
:class:`PositionFrame` says which, and for absolute positions the field's size. Predictions
are made in the same frame and the origin is added back afterwards.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dronefl.logs import GroundTruth, LogError, OnboardLog, PseudoLabels, load_run

POSITION_SCALE_M = 10.0  # m per unit of relative horizontal position (inputs and outputs)
PAPER_FIELD_M = (160.0, 120.0)  # m, width (east) x height (north) of the paper's field
ALTITUDE_SCALE_M = 50.0  # m per unit of altitude
SPEED_SCALE_MPS = 3.0  # m/s per unit of velocity (the drones' speed bound)
BOX_SIZE_SCALE = 10.0  # box width/height multiplier (boxes are a few % of the image)
BOX_DIM, ODOMETRY_DIM = 4, 12
FEATURE_DIM = BOX_DIM + ODOMETRY_DIM + 1  # box, odometry, detected flag
BOX_SIZE_FEATURES = slice(2, 4)  # the box's scaled width and height in a feature vector
ALTITUDE_FEATURE = BOX_DIM + 2  # z / ALTITUDE_SCALE_M in a feature vector


@dataclass(frozen=True)
class PositionFrame:
    """The frame of horizontal positions in features and labels: ``relative`` to the drone's
    (x, y) at time t (position invariance), or absolute around the centre of a
    ``field_m`` = (width, height) m field, in units of half its width."""

    relative: bool = True
    field_m: tuple[float, float] = PAPER_FIELD_M

    def __post_init__(self) -> None:
        if len(self.field_m) != 2 or not all(v > 0 for v in self.field_m):
            raise ValueError(
                f"PositionFrame.field_m must be two positive sizes, got {self.field_m}"
            )

    @property
    def scale_m(self) -> float:
        """Metres per unit of horizontal position in features and model outputs."""
        return POSITION_SCALE_M if self.relative else self.field_m[0] / 2.0

    @property
    def field_centre_m(self) -> tuple[float, float]:
        """Origin (x, y) m of absolute positions: the centre of the field."""
        return (self.field_m[0] / 2.0, self.field_m[1] / 2.0)


@dataclass(frozen=True)
class WindowSpec:
    """How windows are cut: ``past_steps`` L_p, ``future_steps`` L_f, windows every ``stride``
    steps, positions ``relative`` to the drone at t (else absolute in a ``field_m`` = (width,
    height) m field), and the chronological ``train_fraction`` (1.0: every window is for
    training, there is no test set)."""

    past_steps: int = 10
    future_steps: int = 5
    relative: bool = True
    stride: int = 1
    train_fraction: float = 0.8
    field_m: tuple[float, float] = PAPER_FIELD_M

    def __post_init__(self) -> None:
        for name in ("past_steps", "future_steps", "stride"):
            if getattr(self, name) < 1:
                raise ValueError(f"WindowSpec.{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 < self.train_fraction <= 1.0:
            raise ValueError(
                f"WindowSpec.train_fraction must be in (0, 1], got {self.train_fraction}"
            )

    @property
    def frame(self) -> PositionFrame:
        return PositionFrame(self.relative, self.field_m)


@dataclass(frozen=True)
class WindowSet:
    """A batch of windows of one or more drones (numpy; the trainer makes tensors).

    ``features`` (B, L_p, FEATURE_DIM) float32; ``altitude`` (B,) mean odometry altitude over
    the window, m; ``origin`` (B, 2) m; ``labels`` (B, L_f, 2) m relative to ``origin``;
    ``target_ids``, ``drone_ids``, ``t_index`` (B,) which target, drone and time step.
    """

    features: np.ndarray
    altitude: np.ndarray
    origin: np.ndarray
    labels: np.ndarray
    target_ids: np.ndarray
    drone_ids: np.ndarray
    t_index: np.ndarray

    def __len__(self) -> int:
        return int(self.features.shape[0])

    @staticmethod
    def concat(sets: list[WindowSet]) -> WindowSet:
        """All windows of ``sets`` in one set (e.g. the centralized, pooled data)."""
        if not sets:
            raise ValueError("WindowSet.concat needs at least one set")
        return WindowSet(
            *(np.concatenate([getattr(s, k) for s in sets]) for k in WindowSet.__dataclass_fields__)
        )


def window_origin(odometry_t: np.ndarray, frame: PositionFrame) -> np.ndarray:
    """Origin (..., 2) m of the windows whose last odometry readings are ``odometry_t``
    (..., 12): the drone's (x, y) at t in a relative ``frame``, else the field centre."""
    if frame.relative:
        return odometry_t[..., 0:2].astype(np.float64)
    return np.broadcast_to(np.asarray(frame.field_centre_m), odometry_t.shape[:-1] + (2,))


def window_features(
    boxes: np.ndarray,
    detected: np.ndarray,
    odometry: np.ndarray,
    origin: np.ndarray,
    frame: PositionFrame,
) -> np.ndarray:
    """Scaled model inputs (see the module table) for windows of any leading shape.

    ``boxes`` (..., L, 4) normalised (NaN allowed where missed), ``detected`` (..., L) bool,
    ``odometry`` (..., L, 12), ``origin`` (..., 2) m subtracted from odometry x, y (see
    :func:`window_origin`), positions in ``frame``. Returns (..., L, FEATURE_DIM) float32.
    """
    seen = detected[..., None]  # (..., L, 1)
    cx, cy, w, h = np.moveaxis(np.where(seen, boxes, 0.5), -1, 0)  # each (..., L)
    box = np.stack(
        [2 * (cx - 0.5), 2 * (cy - 0.5), w * BOX_SIZE_SCALE, h * BOX_SIZE_SCALE], axis=-1
    )
    box = np.where(seen, box, 0.0)  # (..., L, 4); missed steps carry no box at all
    xy = (odometry[..., 0:2] - origin[..., None, :]) / frame.scale_m
    z = odometry[..., 2:3] / ALTITUDE_SCALE_M
    v = odometry[..., 3:6] / SPEED_SCALE_MPS
    rest = odometry[..., 6:12]
    out = np.concatenate([box, xy, z, v, rest, seen.astype(np.float64)], axis=-1)
    return out.astype(np.float32)


def ground_truth_labels(log: OnboardLog, truth: GroundTruth) -> np.ndarray:
    """True target positions (T, N, 2) m in the log's column order, on the log's time grid."""
    if log.t.shape != truth.t.shape or not np.allclose(log.t, truth.t, atol=1e-6):
        raise LogError(
            f"drone {log.drone_id}: onboard log and ground truth are on different time grids"
        )
    columns = [truth.target_column(int(j)) for j in log.target_ids]
    return truth.target_position[:, columns, :]


def build_windows(
    log: OnboardLog,
    labels: np.ndarray,
    spec: WindowSpec,
    steps: tuple[int, int] | None = None,
) -> WindowSet:
    """Every valid window of the drone's *assigned* targets whose steps all lie in
    ``steps = (start, stop)`` (default: the whole log).

    ``labels`` (T, N, 2) m are target positions on the log's time grid in its column order:
    ground truth (:func:`ground_truth_labels`) or pseudo-labels such as fused EKF tracks (NaN
    where none exists; windows whose future labels are not all finite are dropped).
    """
    n_steps, n_targets = log.detected.shape
    if labels.shape != (n_steps, n_targets, 2):
        raise ValueError(
            f"drone {log.drone_id}: labels must have shape {(n_steps, n_targets, 2)}, "
            f"got {labels.shape}"
        )
    start, stop = (0, n_steps) if steps is None else steps
    lp, lf = spec.past_steps, spec.future_steps
    t = np.arange(start + lp - 1, stop - lf, spec.stride)  # (W,) window times
    past = t[:, None] + np.arange(-lp + 1, 1)[None, :]  # (W, L_p)
    future = t[:, None] + np.arange(1, lf + 1)[None, :]  # (W, L_f)
    odometry = log.odometry.astype(np.float64)
    parts = []
    for column in np.flatnonzero(log.assigned):
        detected = log.detected[past, column]  # (W, L_p)
        future_xy = labels[future, column]  # (W, L_f, 2)
        keep = detected.any(axis=1) & np.isfinite(future_xy).all(axis=(1, 2))
        tk = t[keep]
        origin = window_origin(odometry[tk], spec.frame)
        features = window_features(
            log.boxes[past[keep], column],
            detected[keep],
            odometry[past[keep]],
            origin,
            spec.frame,
        )
        parts.append(
            WindowSet(
                features=features,
                altitude=odometry[past[keep], 2].mean(axis=1).astype(np.float32),
                origin=origin.astype(np.float32),
                labels=(future_xy[keep] - origin[:, None, :]).astype(np.float32),
                target_ids=np.full(tk.size, log.target_ids[column], dtype=np.int32),
                drone_ids=np.full(tk.size, log.drone_id, dtype=np.int32),
                t_index=tk.astype(np.int32),
            )
        )
    if not parts:
        raise ValueError(f"drone {log.drone_id} has no assigned targets")
    return WindowSet.concat(parts)


def split_windows(
    log: OnboardLog, labels: np.ndarray, spec: WindowSpec
) -> tuple[WindowSet, WindowSet]:
    """Chronological train/test split of one drone's windows.

    The first ``train_fraction`` of the steps give the training windows, the rest the test
    windows; no window straddles the split, so no test step is ever seen in training. With
    ``train_fraction`` 1 (online rounds on pseudo-labels) the test set is empty, and so may the
    training set be (no window with a label): the drone then sits the round out.
    """
    n_steps = log.t.shape[0]
    split = int(n_steps * spec.train_fraction)
    train = build_windows(log, labels, spec, (0, split))
    test = build_windows(log, labels, spec, (split, n_steps))
    if spec.train_fraction < 1.0 and (len(train) == 0 or len(test) == 0):
        raise ValueError(
            f"drone {log.drone_id}: too few detected windows for a train/test split "
            f"({len(train)} train, {len(test)} test)"
        )
    return train, test


def load_drone_split(
    run_dir: str | Path, drone_id: int, spec: WindowSpec, labels: str = "ground_truth"
) -> tuple[WindowSet, WindowSet]:
    """Train/test windows of drone ``drone_id`` of a recorded run, labelled by ground truth
    or, with ``labels="tracks"``, by the pseudo-labels the cloud made for it:
    ``tracks_<id>.npz`` (the closed loop's round folders, one file per drone) or, in a folder
    without one, ``tracks.npz`` (a drone's own disk in a deployment, or labels for all)."""
    if labels == "tracks":
        log = OnboardLog.load(Path(run_dir) / f"drone_{drone_id}.npz")
        own = Path(run_dir) / f"tracks_{drone_id}.npz"
        pseudo = PseudoLabels.load(own if own.is_file() else Path(run_dir) / "tracks.npz")
        return split_windows(log, pseudo.for_log(log), spec)
    logs, truth = load_run(run_dir)
    if drone_id not in logs:
        raise LogError(f"{run_dir}: no log of drone {drone_id} (have {sorted(logs)})")
    log = logs[drone_id]
    return split_windows(log, ground_truth_labels(log, truth), spec)
