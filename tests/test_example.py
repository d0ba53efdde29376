"""The README's "Change one part and compare" example runs and means what it says."""

import importlib.util
from pathlib import Path

from dronefl.experiments.episode import EpisodeMetrics

ROOT = Path(__file__).parents[1]


def _example():
    spec = importlib.util.spec_from_file_location(
        "change_one_part", ROOT / "examples" / "change_one_part.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_readme_shows_the_example_file():
    readme = (ROOT / "README.md").read_text()
    source = (ROOT / "examples" / "change_one_part.py").read_text()
    start = source.index("class MissingDetector")
    assert source[start:].strip() in readme


def test_a_detector_that_misses_half_its_detections_predicts_worse(tmp_path, quick_pretrained):
    table = _example().compare(
        tmp_path, miss=0.5, duration=30.0, environment="crop_field", runtime="torch",
        pretrained=quick_pretrained, progress=False, animate=False,
    )  # fmt: skip

    paper = EpisodeMetrics.load(tmp_path / "paper" / "metrics.json")
    missing = EpisodeMetrics.load(tmp_path / "missing" / "metrics.json")
    assert "50% missed" in table and "paper" in table
    # The same world and seed: the targets' paths are identical, only the detections differ.
    assert paper.config == {**missing.config, "out": paper.config["out"]}
    # Windows with half their boxes missing predict worse (measured: 8.1 vs 2.3 m^2).
    assert missing.tracking.prediction_error > 1.5 * paper.tracking.prediction_error
