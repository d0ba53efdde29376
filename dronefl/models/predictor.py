"""On-drone inference: one step's predictions of every target from the last ``L_p`` steps.

:class:`TrajectoryPredictor` builds the same features as training
(:func:`~dronefl.models.windows.window_features`) for each target detected at least once in the
window, runs the transformer on all of them as one batch and adds the window origin back, so
its outputs are world-frame positions in m. Three runtimes give the same numbers:

* ``torch``: the eager model;
* ``torchscript``: the model traced with ``torch.jit.trace`` (no Python per layer);
* ``onnx``: the model exported to ONNX and run by ONNX Runtime on ``threads`` threads, the
  natural runtime on a drone-class CPU.
"""

from __future__ import annotations

import io
import warnings
from typing import Literal

import numpy as np
import torch

from dronefl.models.model import TrajectoryTransformer
from dronefl.models.windows import window_features, window_origin

Runtime = Literal["torch", "torchscript", "onnx"]
RUNTIMES: tuple[str, ...] = ("torch", "torchscript", "onnx")


class TrajectoryPredictor:
    """Predicts the next ``L_f`` positions of each target a drone watches."""

    def __init__(
        self, model: TrajectoryTransformer, runtime: Runtime = "torch", threads: int = 1
    ) -> None:
        if runtime not in RUNTIMES:
            raise ValueError(f"runtime: unknown {runtime!r}; choose one of {RUNTIMES}")
        self.config = model.config
        self.runtime = runtime
        self.threads = threads
        self.model = model.eval()
        self._run = self._compile(runtime)

    def _compile(self, runtime: str):
        lp, f = self.config.past_steps, self.config.input_dim
        example = (torch.zeros(2, lp, f), torch.full((2,), 30.0))
        if runtime == "torch":
            return lambda x, h: self.model(torch.from_numpy(x), torch.from_numpy(h)).numpy()
        if runtime == "torchscript":
            with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                traced = torch.jit.freeze(torch.jit.trace(self.model, example))
            return lambda x, h: traced(torch.from_numpy(x), torch.from_numpy(h)).numpy()
        import onnxruntime

        buffer = io.BytesIO()
        # The tracer warns about the shape checks in forward(); shapes are fixed per model.
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(
                self.model,
                example,
                buffer,
                input_names=["features", "altitude"],
                output_names=["positions"],
                dynamic_axes={
                    "features": {0: "batch"},
                    "altitude": {0: "batch"},
                    "positions": {0: "batch"},
                },
                dynamo=False,
            )
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = self.threads
        options.inter_op_num_threads = 1
        session = onnxruntime.InferenceSession(
            buffer.getvalue(), options, providers=["CPUExecutionProvider"]
        )
        return lambda x, h: session.run(None, {"features": x, "altitude": h})[0]

    def load_state(self, state: dict[str, torch.Tensor]) -> None:
        """Replace the weights (after an FL round) and rebuild the runtime."""
        self.model.load_state_dict(state)
        self.model.eval()
        self._run = self._compile(self.runtime)

    @torch.no_grad()
    def predict(self, odometry: np.ndarray, boxes: np.ndarray, detected: np.ndarray) -> np.ndarray:
        """Predictions ``(N, L_f, 2)`` m (world frame) from the last ``L_p`` steps.

        ``odometry`` ``(L_p, 12)``; ``boxes`` ``(L_p, N, 4)`` normalised (NaN where missed);
        ``detected`` ``(L_p, N)`` bool. Targets not detected in the window get NaN.
        """
        lp = self.config.past_steps
        if odometry.shape != (lp, 12) or boxes.ndim != 3 or boxes.shape[0] != lp:
            raise ValueError(
                f"predict needs odometry ({lp}, 12), boxes ({lp}, N, 4) and detected ({lp}, N); "
                f"got {odometry.shape}, {boxes.shape}, {detected.shape}"
            )
        n = boxes.shape[1]
        out = np.full((n, self.config.future_steps, 2), np.nan)
        columns = np.flatnonzero(detected.any(axis=0))
        if columns.size == 0:
            return out
        odometry = odometry.astype(np.float64)
        origin = window_origin(odometry[-1], self.config.frame)  # (2,)
        features = window_features(
            np.moveaxis(boxes[:, columns], 1, 0),  # (n, L_p, 4)
            detected[:, columns].T,  # (n, L_p)
            np.broadcast_to(odometry, (columns.size, lp, 12)),
            np.broadcast_to(origin, (columns.size, 2)),
            self.config.frame,
        )  # (n, L_p, FEATURE_DIM)
        altitude = np.full(columns.size, odometry[:, 2].mean(), dtype=np.float32)
        positions = self._run(np.ascontiguousarray(features, dtype=np.float32), altitude)
        out[columns] = positions.astype(np.float64) + origin
        return out
