"""The pure-torch ``torchvision::nms`` fallback and the detector's numpy NMS against a
brute-force greedy NMS written out in plain Python."""

import numpy as np
import pytest
import torch

from dronefl.perception.nms_compat import ensure_torchvision_nms, nms_reference
from dronefl.perception.yolo import nms as numpy_nms


def brute_force_nms(boxes: list[list[float]], scores: list[float], threshold: float) -> list[int]:
    """Keep boxes by decreasing score unless one already kept overlaps it with IoU > threshold."""

    def iou(a: list[float], b: list[float]) -> float:
        w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
        h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
        inter = w * h
        union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
        return inter / union

    kept: list[int] = []
    for i in sorted(range(len(scores)), key=lambda k: -scores[k]):
        if all(iou(boxes[i], boxes[k]) <= threshold for k in kept):
            kept.append(i)
    return kept


def random_boxes(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` clustered boxes (many overlaps) with distinct scores."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0, 100, size=(8, 2))[rng.integers(0, 8, n)] + rng.normal(0, 4, (n, 2))
    sizes = rng.uniform(5, 20, size=(n, 2))
    boxes = np.concatenate([centres - sizes / 2, centres + sizes / 2], axis=1)
    return boxes.astype(np.float32), rng.permutation(n).astype(np.float32) / n


@pytest.mark.parametrize("threshold", [0.3, 0.5, 0.7])
@pytest.mark.parametrize("seed", [0, 1])
def test_fallback_and_numpy_nms_match_brute_force(threshold: float, seed: int) -> None:
    boxes, scores = random_boxes(300, seed)
    expected = brute_force_nms(boxes.tolist(), scores.tolist(), threshold)
    fallback = nms_reference(torch.from_numpy(boxes), torch.from_numpy(scores), threshold)
    assert fallback.tolist() == expected
    assert numpy_nms(boxes, scores, threshold).tolist() == expected


def test_fallback_spans_several_blocks() -> None:
    boxes, scores = random_boxes(2500, seed=3)  # more rows than one IoU block (1024)
    expected = brute_force_nms(boxes.tolist(), scores.tolist(), 0.5)
    assert (
        nms_reference(torch.from_numpy(boxes), torch.from_numpy(scores), 0.5).tolist() == expected
    )


def test_torchvision_nms_works_after_ensure() -> None:
    ensure_torchvision_nms()
    ensure_torchvision_nms()  # idempotent
    import torchvision

    boxes, scores = random_boxes(100, seed=4)
    kept = torchvision.ops.nms(torch.from_numpy(boxes), torch.from_numpy(scores), 0.5)
    assert kept.tolist() == brute_force_nms(boxes.tolist(), scores.tolist(), 0.5)


def test_empty_input() -> None:
    assert nms_reference(torch.zeros((0, 4)), torch.zeros(0), 0.5).tolist() == []
    assert numpy_nms(np.zeros((0, 4)), np.zeros(0), 0.5).tolist() == []
