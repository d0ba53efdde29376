"""On-drone inference: absolute outputs, targets without detections, runtimes agree."""

import numpy as np
import pytest
import torch

from dronefl.models.model import build_model, predictor_config
from dronefl.models.predictor import TrajectoryPredictor
from dronefl.models.windows import PositionFrame, window_features


def _step(rng):
    odometry = rng.normal(size=(10, 12)).astype(np.float32)
    odometry[:, 0:3] += (40.0, 30.0, 30.0)  # drone near (40, 30) m, 30 m up
    boxes = rng.uniform(0.2, 0.8, size=(10, 3, 4)).astype(np.float32)
    detected = np.ones((10, 3), dtype=bool)
    detected[:, 2] = False  # target 3 never seen
    boxes[:, 2] = np.nan
    return odometry, boxes, detected


def test_predict_adds_the_drone_position_back():
    rng = np.random.default_rng(0)
    odometry, boxes, detected = _step(rng)
    model = build_model(predictor_config("dronefl")).eval()
    out = TrajectoryPredictor(model, runtime="torch").predict(odometry, boxes, detected)
    assert out.shape == (3, 5, 2)
    assert np.isnan(out[2]).all()  # no detection in the window: no prediction
    origin = odometry[-1, 0:2].astype(np.float64)
    features = window_features(boxes[:, 0], detected[:, 0], odometry, origin, PositionFrame())
    altitude = torch.tensor([odometry[:, 2].astype(np.float64).mean()], dtype=torch.float32)
    with torch.no_grad():
        relative = model(torch.from_numpy(features)[None], altitude)[0].numpy()
    np.testing.assert_allclose(out[0], relative + origin, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("runtime", ["torchscript", "onnx"])
def test_compiled_runtimes_match_eager(runtime):
    rng = np.random.default_rng(1)
    step = _step(rng)
    model = build_model(predictor_config("dronefl")).eval()
    eager = TrajectoryPredictor(model, runtime="torch").predict(*step)
    other = TrajectoryPredictor(model, runtime=runtime).predict(*step)
    np.testing.assert_allclose(other, eager, rtol=1e-4, atol=1e-3)


def test_bad_step_shapes_are_rejected():
    predictor = TrajectoryPredictor(build_model(predictor_config("plain")), runtime="torch")
    with pytest.raises(ValueError, match="predict needs odometry"):
        predictor.predict(np.zeros((9, 12)), np.zeros((10, 2, 4)), np.ones((10, 2), bool))
