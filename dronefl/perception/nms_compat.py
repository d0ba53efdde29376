"""A pure-torch CPU ``torchvision::nms`` (and ``qnms``) for when torchvision's C++ ops fail to load.

The registry's torchvision wheel is a CUDA build; with the CPU torch its ``_C`` extension fails
to load and ``import torchvision`` (hence Ultralytics train/predict) dies with
``operator torchvision::nms does not exist``. :func:`ensure_torchvision_nms` registers an
equivalent operator through ``torch.library`` *before* torchvision is imported, and only when
the compiled one is missing, so a working torchvision is never shadowed. torchvision then
believes all its C++ ops are missing, so the guard in ``torchvision.ops.boxes`` (whose only
compiled calls are ``nms``/``qnms``) is replaced by one that checks for the registered op.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import torch

#: Rows of the IoU matrix built at once by :func:`nms_reference`.
_BLOCK = 1024
_LIBRARY: torch.library.Library | None = None


def nms_reference(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Greedy non-maximum suppression with torchvision's semantics.

    ``boxes`` ``(N, 4)`` as ``(x1, y1, x2, y2)``, ``scores`` ``(N,)``. Going down the scores, a
    box is kept unless its IoU with an already kept box is ``> iou_threshold``. Returns the kept
    indices ``(K,)`` int64, by decreasing score. The IoU matrix is built ``_BLOCK`` rows at a
    time, so memory stays ``O(_BLOCK * N)``.
    """
    n = int(scores.shape[0])
    order = torch.argsort(scores, descending=True, stable=True)
    sorted_boxes = boxes.detach().to(torch.float32)[order]  # (N, 4)
    wh = (sorted_boxes[:, 2:] - sorted_boxes[:, :2]).clamp(min=0)
    areas = wh[:, 0] * wh[:, 1]  # (N,)
    removed = np.zeros(n, dtype=bool)
    keep: list[int] = []
    for start in range(0, n, _BLOCK):
        rows = sorted_boxes[start : start + _BLOCK]  # (B, 4)
        lt = torch.maximum(rows[:, None, :2], sorted_boxes[None, :, :2])  # (B, N, 2)
        rb = torch.minimum(rows[:, None, 2:], sorted_boxes[None, :, 2:])  # (B, N, 2)
        inter = (rb - lt).clamp(min=0).prod(dim=-1)  # (B, N)
        union = areas[start : start + _BLOCK, None] + areas[None, :] - inter
        overlaps = (inter / union.clamp(min=1e-12) > iou_threshold).numpy()  # (B, N)
        for r in range(rows.shape[0]):
            i = start + r
            if removed[i]:
                continue
            keep.append(i)
            removed[i + 1 :] |= overlaps[r, i + 1 :]
    return order[torch.as_tensor(keep, dtype=torch.int64)]


def _compiled_nms_available() -> bool:
    """True when torchvision's compiled ``nms`` exists or loads from its ``_C`` extension."""
    if hasattr(torch.ops.torchvision, "nms"):
        return True
    spec = importlib.util.find_spec("torchvision")
    if spec is None or not spec.submodule_search_locations:
        return False
    for folder in spec.submodule_search_locations:
        for lib in Path(folder).glob("_C*.so"):
            try:
                torch.ops.load_library(str(lib))
            except (OSError, RuntimeError):
                continue
            if hasattr(torch.ops.torchvision, "nms"):
                return True
    return False


def ensure_torchvision_nms() -> bool:
    """Register the pure-torch ``torchvision::nms`` if the compiled op is missing.

    Call before importing torchvision or Ultralytics (it imports torchvision). Returns ``True``
    when the fallback is (or already was) registered, ``False`` when the compiled op is used.
    Idempotent.
    """
    global _LIBRARY
    if _LIBRARY is not None:
        return True
    if _compiled_nms_available():
        return False
    library = torch.library.Library("torchvision", "DEF")
    # torchvision's import registers fake kernels for both ops, so both must exist; ``qnms``
    # receives the integer representation of quantized boxes, which the same greedy rule handles.
    for op in ("nms", "qnms"):
        library.define(f"{op}(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
        library.impl(op, nms_reference, "CPU")
    _LIBRARY = library
    # torchvision marks all its C++ ops missing and ``torchvision.ops.nms`` refuses to run;
    # its box module only dispatches to ``nms``/``qnms``, so lift the guard there alone.
    import torchvision.ops.boxes as tv_boxes

    tv_boxes._assert_has_ops = _assert_nms_registered
    return True


def _assert_nms_registered() -> None:
    """The guard ``torchvision.ops.boxes`` runs before dispatching to ``torchvision::nms``."""
    if not hasattr(torch.ops.torchvision, "nms"):
        raise RuntimeError("torchvision::nms is not registered; call ensure_torchvision_nms()")
