"""`dronefl image-baseline` end to end on a short recording: both models scored on the same
held-out cells, the image model's input and size stated, weights and plot written."""

import numpy as np
import pytest

from dronefl.config import load_scenario
from dronefl.experiments.image_baseline import ImageBaselineConfig, run_image_baseline


@pytest.mark.slow
def test_image_baseline_scores_both_models_on_both_environments(tmp_path):
    config = ImageBaselineConfig(
        load_scenario("case1"), tmp_path, duration=16.0, epochs=2, frame_px=16, progress=False
    )
    results = run_image_baseline(config)
    assert results["model_input"] == "frames"
    image = results["image_model"]
    assert image["parameters"] > 10_000 and len(image["train_loss"]) == 2
    assert image["train_seconds_per_epoch"] > 0 and image["inference_ms_per_sample"] > 0
    for model in ("image", "boxes"):
        for where in ("crop_field_held_out", "orchard"):
            scores = results["mse"][model][where]
            assert set(scores) == {"1", "2"}, scores
            assert all(np.isfinite(v) and v > 0 for v in scores.values())
    # By the target's distance from the drone: both models on the same cells, every bin.
    by_offset = results["mse_by_offset"]
    for place in ("crop_field_held_out", "orchard"):
        image_bins, box_bins = (by_offset[m][place] for m in ("image", "boxes"))
        assert len(image_bins["mse"]) == len(by_offset["edges_m"])
        assert image_bins["cells"] == box_bins["cells"] and sum(image_bins["cells"]) > 0
    assert results["jpeg_kb_per_frame"]["orchard"] > 10  # 640 x 640 frames at q90
    with np.load(tmp_path / "image_model.npz") as weights:
        assert sum(weights[k].size for k in weights.files) == image["parameters"]
    assert (tmp_path / "image_baseline.png").stat().st_size > 10_000
    # Rendered once: the frames are cached beside each recording.
    assert (tmp_path / "crop_field" / "frames_16px_q90.npz").is_file()
    assert (tmp_path / "orchard" / "frames_16px_q90.npz").is_file()
