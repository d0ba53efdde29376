"""The ``yolo`` detector: the frozen YOLO11n network on rendered frames, run by ONNX Runtime.

The network (trained by :mod:`dronefl.perception.training`, shipped as
``dronefl/assets/detector.onnx``) takes an RGB ``imgsz x imgsz`` frame scaled to ``[0, 1]`` and
returns ``(1, 4 + C, A)``: for each of ``A`` anchors a box ``(cx, cy, w, h)`` in input pixels
and ``C`` class scores. Decoding, all in numpy:

1. letterbox the detector frame (640 x 640 by default) to ``imgsz`` (a plain resize when square);
2. keep anchors whose best class score is ``>= conf_threshold``;
3. class-agnostic NMS at ``iou_threshold`` (one vehicle must not become two targets);
4. per class the most confident box, reported as target id ``class + 1`` with its box
   normalised to the detector frame, clipped to ``[0, 1]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import onnx
import onnxruntime as ort
from onnx import numpy_helper

from dronefl.perception.base import Detector
from dronefl.perception.render import SceneRenderer
from dronefl.perception.training import DETECTOR_ASSET, DETECTOR_SIDECAR, DetectorSidecar
from dronefl.types import CameraView, Detection

if TYPE_CHECKING:
    from dronefl.sim.world import World


def shipped_detector_path() -> Path:
    """Path of the ONNX detector that ships inside the package."""
    return Path(str(resources.files("dronefl") / "assets" / DETECTOR_ASSET))


@dataclass(frozen=True)
class Letterbox:
    """How a frame of ``size`` ``(H, W)`` px maps into the square network input: scaled by
    ``scale`` and padded by ``pad`` ``(x, y)`` px."""

    size: tuple[int, int]
    scale: float
    pad: tuple[float, float]


def _check_finite_weights(path: Path) -> None:
    """Raise ValueError naming ``path`` if a weight of the ONNX model is NaN or infinite."""
    model = onnx.load(str(path))
    for tensor in model.graph.initializer:
        values = numpy_helper.to_array(tensor)
        if np.issubdtype(values.dtype, np.floating) and not np.isfinite(values).all():
            raise ValueError(f"{path}: weight {tensor.name!r} holds NaN or inf values")


def letterbox(image: np.ndarray, imgsz: int) -> tuple[np.ndarray, Letterbox]:
    """Resize ``image`` ``(H, W, 3)`` uint8 keeping its aspect and pad it (grey 114, as in
    training) to ``(imgsz, imgsz, 3)``; returns the padded frame and the mapping."""
    h, w = image.shape[:2]
    scale = min(imgsz / h, imgsz / w)
    new_w, new_h = round(w * scale), round(h * scale)
    resized = cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_AREA)
    pad_x, pad_y = (imgsz - new_w) / 2, (imgsz - new_h) / 2
    out = np.full((imgsz, imgsz, 3), 114, dtype=np.uint8)
    top, left = int(round(pad_y - 0.1)), int(round(pad_x - 0.1))
    out[top : top + new_h, left : left + new_w] = resized
    return out, Letterbox((h, w), scale, (left, top))


def nms(boxes: np.ndarray, scores: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Greedy NMS: ``boxes`` ``(N, 4)`` as ``(x1, y1, x2, y2)``, ``scores`` ``(N,)``. Returns the
    kept indices by decreasing score (a box goes if its IoU with a kept one is ``> iou``)."""
    order = np.argsort(-scores, kind="stable")
    areas = np.prod(np.clip(boxes[:, 2:] - boxes[:, :2], 0, None), axis=1)
    keep = []
    while order.size:
        best, rest = order[0], order[1:]
        keep.append(best)
        lt = np.maximum(boxes[best, :2], boxes[rest, :2])
        rb = np.minimum(boxes[best, 2:], boxes[rest, 2:])
        inter = np.prod(np.clip(rb - lt, 0, None), axis=1)
        iou = inter / np.maximum(areas[best] + areas[rest] - inter, 1e-12)
        order = rest[iou <= iou_threshold]
    return np.asarray(keep, dtype=np.int64)


class YoloDetector(Detector):
    """Frozen YOLO11n detector behind the :class:`Detector` interface (see module doc).

    ``weights`` defaults to the shipped ONNX file. ``renderer`` draws the frame when a view comes
    without an image (it must hold the view's targets). ``target_ids`` (default: any class)
    restricts the reports to the vehicles of the mission. ONNX Runtime uses ``threads`` intra-op
    threads (1 by default: one core of a drone's companion computer).
    """

    name = "yolo"

    def __init__(
        self,
        weights: Path | None = None,
        renderer: SceneRenderer | None = None,
        conf_threshold: float = 0.25,
        iou_threshold: float = 0.5,
        threads: int = 1,
        target_ids: tuple[int, ...] | None = None,
    ) -> None:
        path = weights or shipped_detector_path()
        if not path.is_file():
            raise FileNotFoundError(
                f"no detector weights at {path}: run `dronefl detector train` or reinstall"
            )
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        try:
            self.session = ort.InferenceSession(
                str(path), options, providers=["CPUExecutionProvider"]
            )
        except Exception as exc:  # onnxruntime raises its own untyped errors on bad files
            reason = " ".join(str(exc).split())[:300]
            raise ValueError(f"{path} is not a readable ONNX detector ({reason})") from None
        model_input, output = self.session.get_inputs()[0], self.session.get_outputs()[0]
        in_shape, out_shape = model_input.shape, output.shape
        if (
            len(in_shape) != 4
            or in_shape[1] != 3
            or not isinstance(in_shape[-1], int)
            or len(out_shape) != 3
            or not isinstance(out_shape[1], int)
            or out_shape[1] < 5
        ):
            raise ValueError(
                f"{path}: not a YOLO detector (input {in_shape}, output {out_shape}; expected "
                "(1, 3, S, S) -> (1, 4 + classes, candidates))"
            )
        _check_finite_weights(path)
        self.input_name = model_input.name
        self.imgsz = int(in_shape[-1])
        self.n_classes = int(out_shape[1]) - 4
        self.renderer = renderer
        self.conf_threshold = conf_threshold
        self.iou_threshold = iou_threshold
        self.target_ids = target_ids

    @classmethod
    def for_world(cls, world: World) -> YoloDetector:
        """The shipped detector on frames rendered from ``world`` (its environment, vehicles
        and camera), reporting only the scenario's target ids."""
        scenario = world.scenario
        renderer = SceneRenderer(
            world.camera, scenario.vehicle, world.environment, scenario.target_ids
        )
        return cls(renderer=renderer, target_ids=scenario.target_ids)

    @staticmethod
    def sidecar(weights: Path | None = None) -> DetectorSidecar:
        """The record shipped beside the ``weights`` (default: the shipped ones): training
        command, data, metrics."""
        return DetectorSidecar.load(
            (weights or shipped_detector_path()).with_name(DETECTOR_SIDECAR)
        )

    def close(self) -> None:
        """Free the renderer's OpenGL context, if the detector has a renderer."""
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None

    def detect(self, view: CameraView) -> tuple[Detection, ...]:
        """Detections in ``view.image`` (rendered first if the view carries none)."""
        image = view.image
        if image is None:
            if self.renderer is None:
                raise ValueError("view has no image and the detector has no renderer")
            image = self.renderer.render_view(view)
        return self.detect_image(image)

    def detect_image(self, image: np.ndarray) -> tuple[Detection, ...]:
        """Detections in one RGB frame ``(H, W, 3)`` uint8, boxes normalised to that frame."""
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(
                f"expected an (H, W, 3) uint8 RGB frame, got {image.shape} {image.dtype}"
            )
        padded, box = letterbox(image, self.imgsz)
        x = padded.transpose(2, 0, 1)[None].astype(np.float32) / 255.0  # (1, 3, S, S)
        raw = self.session.run(None, {self.input_name: x})[0][0].T  # (A, 4 + C)
        scores = raw[:, 4:]
        classes = scores.argmax(axis=1)
        confidence = scores[np.arange(len(scores)), classes]
        keep = confidence >= self.conf_threshold
        xywh, classes, confidence = raw[keep, :4], classes[keep], confidence[keep]
        corners = np.concatenate([xywh[:, :2] - xywh[:, 2:] / 2, xywh[:, :2] + xywh[:, 2:] / 2], 1)
        kept = nms(corners, confidence, self.iou_threshold)
        h, w = box.size
        detections: dict[int, Detection] = {}
        for k in kept:  # by decreasing confidence: the first box of a class wins
            target_id = int(classes[k]) + 1
            if target_id in detections or (
                self.target_ids is not None and target_id not in self.target_ids
            ):
                continue
            x1, y1, x2, y2 = (corners[k] - np.array([*box.pad, *box.pad])) / box.scale
            x1, x2 = np.clip([x1, x2], 0, w) / w
            y1, y2 = np.clip([y1, y2], 0, h) / h
            normalised = ((x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1)
            detections[target_id] = Detection(
                target_id, tuple(float(v) for v in normalised), float(confidence[k])
            )
        return tuple(detections[i] for i in sorted(detections))
