"""Detector dataset: labels follow the projection detector's visibility rule; folder layout."""

from pathlib import Path

import numpy as np
import yaml

from dronefl.config import load_scenario
from dronefl.perception.dataset import DatasetConfig, label_scene, read_scenes, write_dataset
from dronefl.sim.camera import PinholeCamera
from dronefl.sim.environment import FarmEnvironment
from dronefl.types import TargetState

SCENARIO = load_scenario("case3")
CAMERA = PinholeCamera.from_spec(SCENARIO.camera)


def vehicle(target_id: int, x: float, y: float) -> TargetState:
    return TargetState(target_id, np.array([x, y]), np.zeros(2), 0.0)


def test_labels_follow_visibility_rule() -> None:
    env = FarmEnvironment("crop_field", SCENARIO.field)
    camera = np.array([80.0, 62.5, 30.0])
    targets = (
        vehicle(1, 80.0, 62.5),  # at nadir: fully visible
        vehicle(2, 80.0 + 25.17, 62.5),  # centre on the right image border: half inside
        vehicle(3, 80.0 + 60.0, 62.5),  # far outside the image
    )
    scene = label_scene(CAMERA, SCENARIO, env, camera, 0.0, targets, min_visible=0.5)
    assert scene.target_ids.tolist() == [1]
    np.testing.assert_allclose(scene.boxes[0, :2], [0.5, 0.5])
    # at nadir the hull is the 4 m x 2 m roof, 30 - 1.5 = 28.5 m from the camera
    f = CAMERA.focal_px
    np.testing.assert_allclose(scene.boxes[0, 2], 4.0 * f / 28.5 / 1280, rtol=1e-9)
    np.testing.assert_allclose(scene.boxes[0, 3], 2.0 * f / 28.5 / 720, rtol=1e-9)


def test_orchard_canopy_hides_a_vehicle() -> None:
    env = FarmEnvironment("orchard", SCENARIO.field)
    tree = env.trees[len(env.trees) // 2]
    under = vehicle(1, tree[0], tree[1])  # parked right under a canopy
    scene = label_scene(CAMERA, SCENARIO, env, np.array([*tree, 40.0]), 0.0, (under,), 0.5)
    assert scene.target_ids.size == 0


def test_write_dataset_layout(tmp_path: Path) -> None:
    config = DatasetConfig(train_per_env=2, val_per_env=1, test_per_env=1, seed=3)
    counts = write_dataset(tmp_path, config)
    assert counts == {"train": 4, "val": 2, "test_crop_field": 1, "test_orchard": 1}
    for split, n in counts.items():
        images = sorted((tmp_path / "images" / split).glob("*.jpg"))
        labels = sorted((tmp_path / "labels" / split).glob("*.txt"))
        assert len(images) == len(labels) == n
        for label in labels:
            for line in label.read_text().splitlines():
                cls, *box = line.split()
                assert 0 <= int(cls) < 8 and all(0.0 <= float(v) <= 1.0 for v in box)
        assert len(read_scenes(tmp_path / "scenes" / f"{split}.jsonl")) == n
    data = yaml.safe_load((tmp_path / "data_orchard.yaml").read_text())
    assert data["test"] == "images/test_orchard" and len(data["names"]) == 8
