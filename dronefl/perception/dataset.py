"""Detector dataset: rendered camera frames with exact YOLO labels from the projection geometry.

Each frame draws a random scene: an environment (``crop_field`` or ``orchard``), a camera at a
random point over the field at altitude ``U(altitude_min, altitude_max)`` m with yaw 0 (the
gimbal of the simulator), and a random subset of the palette's vehicles placed in and around the
camera footprint (so several are in view and some are cut by the image border). Most vehicles sit
on a lane (the simulator's paths), heading east or west with a small wobble; the rest stand
anywhere on open ground (headlands in the orchard) with any heading. Vehicles keep ``5`` m apart.

A vehicle is labelled (class = target id - 1) with the box of
:func:`~dronefl.perception.projection.vehicle_boxes` when it passes the projection detector's
visibility rule: ``inside_fraction x unoccluded_fraction >= min_visible`` (a 5 x 3 roof grid tested
with :meth:`FarmEnvironment.visible`). The folder follows the Ultralytics layout::

    DIR/images/{train,val,test_crop_field,test_orchard}/*.jpg
    DIR/labels/<same>/*.txt          one "class cx cy w h" line per labelled vehicle
    DIR/scenes/<split>.jsonl         the true scene of every frame (for the evaluation)
    DIR/data.yaml                    Ultralytics dataset file (train, val; test = both test sets)
    DIR/data_<environment>.yaml      the same with test = that environment's held-out frames
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from dronefl.config import Environment, Scenario, load_scenario
from dronefl.perception.palette import COLOUR_NAMES, MAX_TARGETS
from dronefl.perception.projection import ProjectionNoise, visible_boxes
from dronefl.perception.render import SceneRenderer
from dronefl.serialize import load_result, save_result
from dronefl.sim.camera import PinholeCamera
from dronefl.sim.environment import FarmEnvironment
from dronefl.types import TargetState

#: Environments the detector is trained and tested on.
DATASET_ENVIRONMENTS: tuple[Environment, ...] = ("crop_field", "orchard")
#: Minimum distance between two vehicles' centres, m.
MIN_SEPARATION = 5.0


@dataclass(frozen=True)
class DatasetConfig:
    """What :func:`write_dataset` renders: frame counts per environment, altitudes in m."""

    train_per_env: int = 800
    val_per_env: int = 80
    test_per_env: int = 150
    altitude_min: float = 15.0
    altitude_max: float = 70.0
    lane_share: float = 0.8
    min_visible: float = ProjectionNoise().min_visible
    jpeg_quality: int = 95
    seed: int = 0
    scenario: str = "case3"

    def __post_init__(self) -> None:
        if min(self.train_per_env, self.val_per_env, self.test_per_env) < 1:
            raise ValueError("every split needs at least one frame per environment")
        if not 0 < self.altitude_min < self.altitude_max:
            raise ValueError(
                f"need 0 < altitude_min < altitude_max, got {self.altitude_min}, "
                f"{self.altitude_max}"
            )


@dataclass(frozen=True)
class DatasetManifest:
    """``dataset.json``: the ``config`` that rendered the dataset and its ``frames`` per split
    (``train``, ``val``, ``test_<environment>``)."""

    config: DatasetConfig
    frames: dict[str, int]

    @classmethod
    def load(cls, dataset: Path) -> DatasetManifest:
        """The manifest of the dataset folder ``dataset``; :class:`~dronefl.serialize.ResultError`
        if it has none or a bad one."""
        return load_result(cls, dataset / "dataset.json")


@dataclass(frozen=True)
class LabelledScene:
    """One frame's true scene and its labels: ``boxes`` ``(K, 4)`` normalised cx, cy, w, h of
    the labelled ``target_ids`` ``(K,)``; ``visible`` their visible fractions ``(K,)``."""

    environment: str
    camera_position: np.ndarray  # (3,) m
    yaw: float
    targets: tuple[TargetState, ...]
    target_ids: np.ndarray  # (K,)
    boxes: np.ndarray  # (K, 4)
    visible: np.ndarray  # (K,)

    def to_json(self) -> dict:
        """JSON-ready record."""
        return {
            "environment": self.environment,
            "camera_position": self.camera_position.tolist(),
            "yaw": self.yaw,
            "targets": [[t.target_id, *t.position.tolist(), t.heading] for t in self.targets],
            "labels": [
                [int(i), *b.tolist(), float(v)]
                for i, b, v in zip(self.target_ids, self.boxes, self.visible, strict=True)
            ],
        }

    @classmethod
    def from_json(cls, record: dict) -> LabelledScene:
        """Inverse of :meth:`to_json`; raises ValueError on a wrong shape or a non-finite
        number."""
        labels = np.asarray(record["labels"], dtype=float)
        labels = labels.reshape(0, 6) if labels.size == 0 else labels
        camera = np.asarray(record["camera_position"], dtype=float)
        targets = np.asarray(record["targets"], dtype=float).reshape(-1, 4)
        if labels.ndim != 2 or labels.shape[1] != 6 or camera.shape != (3,):
            raise ValueError("labels must be rows of 6 numbers and camera_position 3 numbers")
        if not all(np.isfinite(a).all() for a in (labels, camera, targets, float(record["yaw"]))):
            raise ValueError("non-finite number")
        return cls(
            environment=record["environment"],
            camera_position=np.asarray(record["camera_position"], dtype=float),
            yaw=float(record["yaw"]),
            targets=tuple(
                TargetState(int(i), np.array([x, y]), np.zeros(2), float(h))
                for i, x, y, h in record["targets"]
            ),
            target_ids=labels[:, 0].astype(int),
            boxes=labels[:, 1:5],
            visible=labels[:, 5],
        )


def label_scene(
    camera: PinholeCamera,
    scenario: Scenario,
    environment: FarmEnvironment,
    camera_position: np.ndarray,
    yaw: float,
    targets: tuple[TargetState, ...],
    min_visible: float,
) -> LabelledScene:
    """Labels of ``targets`` seen from ``camera_position`` with the projection detector's rule."""
    if not targets:
        empty = np.zeros(0)
        return LabelledScene(
            environment.kind, camera_position, yaw, targets, empty.astype(int),
            np.zeros((0, 4)), empty,
        )  # fmt: skip
    positions = np.array([t.position for t in targets])
    headings = np.array([t.heading for t in targets])
    boxes, visible = visible_boxes(
        camera, scenario.vehicle, environment, camera_position, yaw, positions, headings
    )
    keep = visible >= min_visible
    ids = np.array([t.target_id for t in targets])
    return LabelledScene(
        environment.kind, camera_position, yaw, targets, ids[keep], boxes[keep], visible[keep]
    )


def sample_scene(
    rng: np.random.Generator,
    camera: PinholeCamera,
    scenario: Scenario,
    environment: FarmEnvironment,
    config: DatasetConfig,
) -> tuple[np.ndarray, tuple[TargetState, ...]]:
    """A random camera position ``(3,)`` m and vehicles around its footprint (see module doc)."""
    field = scenario.field
    altitude = rng.uniform(config.altitude_min, config.altitude_max)
    centre = rng.uniform([0.0, 0.0], [field.width, field.height])
    half = 1.15 * np.array(camera.footprint_half_extent(altitude))
    lo = np.maximum(centre - half, 0.0)
    hi = np.minimum(centre + half, [field.width, field.height])
    n_vehicles = int(rng.integers(2, MAX_TARGETS + 1))
    ids = np.sort(rng.choice(np.arange(1, MAX_TARGETS + 1), size=n_vehicles, replace=False))
    placed: list[TargetState] = []
    for target_id in ids:
        for _ in range(30):
            state = _random_vehicle(rng, int(target_id), lo, hi, scenario, environment, config)
            if all(np.linalg.norm(state.position - p.position) >= MIN_SEPARATION for p in placed):
                placed.append(state)
                break
    return np.array([centre[0], centre[1], altitude]), tuple(placed)


def _random_vehicle(
    rng: np.random.Generator,
    target_id: int,
    lo: np.ndarray,
    hi: np.ndarray,
    scenario: Scenario,
    environment: FarmEnvironment,
    config: DatasetConfig,
) -> TargetState:
    """One vehicle inside the box ``lo``-``hi`` (m): on a lane, or free on open ground."""
    field = scenario.field
    x = rng.uniform(lo[0], hi[0])
    in_headland = x < field.headland or x > field.width - field.headland
    on_lane = rng.random() < config.lane_share or (
        environment.kind == "orchard" and not in_headland
    )
    if on_lane:
        lanes = np.arange(field.n_lanes)
        lane_y = np.array([field.lane_y(k) for k in lanes])
        candidates = lane_y[(lane_y >= lo[1]) & (lane_y <= hi[1])]
        y = rng.choice(candidates if candidates.size else lane_y) + rng.normal(0.0, 0.25)
        heading = rng.choice([0.0, np.pi]) + rng.normal(0.0, 0.1)
    else:
        y = rng.uniform(lo[1], hi[1])
        heading = rng.uniform(-np.pi, np.pi)
    return TargetState(target_id, np.array([x, y]), np.zeros(2), float(heading))


def write_dataset(
    out: Path, config: DatasetConfig, progress: Callable[[Iterator], Iterator] | None = None
) -> dict[str, int]:
    """Render the dataset into ``out`` (see module doc); returns frames per split.

    Each (split, environment) draws from its own seeded stream, so the held-out frames are
    independent of the training frames and of the split sizes.
    """
    scenario = load_scenario(config.scenario)
    camera = PinholeCamera.from_spec(scenario.camera)
    splits = {"train": config.train_per_env, "val": config.val_per_env, "test": config.test_per_env}
    jobs = []
    for env_index, kind in enumerate(DATASET_ENVIRONMENTS):
        for split_index, (split, n) in enumerate(splits.items()):
            folder = f"test_{kind}" if split == "test" else split
            jobs += [(kind, folder, (config.seed, env_index, split_index), k) for k in range(n)]
    counts: dict[str, int] = {}
    envs = {kind: FarmEnvironment(kind, scenario.field) for kind in DATASET_ENVIRONMENTS}
    renderers = {kind: SceneRenderer(camera, scenario.vehicle, envs[kind]) for kind in envs}
    streams: dict[tuple[int, int, int], np.random.Generator] = {}
    records: dict[str, list[dict]] = {}
    for kind, folder, stream, k in progress(iter(jobs)) if progress else jobs:
        env = envs[kind]
        rng = streams.setdefault(stream, np.random.default_rng(np.random.SeedSequence(stream)))
        position, targets = sample_scene(rng, camera, scenario, env, config)
        scene = label_scene(camera, scenario, env, position, 0.0, targets, config.min_visible)
        image = renderers[kind].render(position, 0.0, targets)
        name = f"{kind}_{k:05d}"
        (out / "images" / folder).mkdir(parents=True, exist_ok=True)
        (out / "labels" / folder).mkdir(parents=True, exist_ok=True)
        Image.fromarray(image).save(
            out / "images" / folder / f"{name}.jpg", quality=config.jpeg_quality
        )
        lines = [
            f"{i - 1} " + " ".join(f"{v:.6f}" for v in box)
            for i, box in zip(scene.target_ids, scene.boxes, strict=True)
        ]
        (out / "labels" / folder / f"{name}.txt").write_text("\n".join(lines) + "\n" * bool(lines))
        records.setdefault(folder, []).append({"image": f"{name}.jpg", **scene.to_json()})
        counts[folder] = counts.get(folder, 0) + 1
    for renderer in renderers.values():
        renderer.close()
    (out / "scenes").mkdir(parents=True, exist_ok=True)
    for folder, rows in records.items():
        text = "\n".join(json.dumps(r) for r in rows) + "\n"
        (out / "scenes" / f"{folder}.jsonl").write_text(text)
    names = {i: f"target{i + 1}_{COLOUR_NAMES[i]}" for i in range(MAX_TARGETS)}
    base = {"path": str(out.resolve()), "train": "images/train", "val": "images/val",
            "names": names}  # fmt: skip
    tests = [f"images/test_{kind}" for kind in DATASET_ENVIRONMENTS]
    (out / "data.yaml").write_text(yaml.safe_dump({**base, "test": tests}, sort_keys=False))
    for kind in DATASET_ENVIRONMENTS:
        data = {**base, "test": f"images/test_{kind}"}
        (out / f"data_{kind}.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    save_result(out / "dataset.json", DatasetManifest(config, counts))
    return counts


def read_scenes(path: Path) -> list[tuple[str, LabelledScene]]:
    """The ``(image file name, scene)`` records of one ``scenes/<split>.jsonl`` file."""
    if not path.is_file():
        raise FileNotFoundError(f"no scene records at {path}: run `dronefl detector dataset`")
    rows = []
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: unreadable scene records ({exc})") from None
    for n, line in enumerate(lines, start=1):
        try:
            record = json.loads(line)
            rows.append((record["image"], LabelledScene.from_json(record)))
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{path}:{n}: corrupt scene record ({exc})") from None
    if not rows:
        raise ValueError(f"{path}: no scene records")
    return rows
