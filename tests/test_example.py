"""The README's "Change one part and compare" example runs and means what it says."""

import importlib.util
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from dronefl.results.episode import EpisodeMetrics

ROOT = Path(__file__).parents[1]


def _load(name: str):
    """``examples/<name>.py`` as a module (the examples are scripts, not a package)."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_readme_shows_the_example_file():
    readme = (ROOT / "README.md").read_text()
    source = (ROOT / "examples" / "change_one_part.py").read_text()
    start = source.index("class MissingDetector")
    assert source[start:].strip() in readme


def test_a_detector_that_misses_half_its_detections_predicts_worse(tmp_path, quick_pretrained):
    table = _load("change_one_part").compare(
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


def _episodes(scenario, values):
    """Stand-ins for EpisodeMetrics with the attributes compare() reads, by seed."""
    return {
        seed: SimpleNamespace(
            seed=seed,
            scenario=scenario,
            tracking=SimpleNamespace(prediction_error=p, tracking_distance=d, tracking_error=e),
        )
        for seed, (p, d, e) in values.items()
    }


def test_compare_runs_tabulates_the_shared_seeds_against_the_first_variant(tmp_path):
    example = _load("compare_runs")
    base = _episodes("case2", {0: (2.0, 20.0, 1.0), 1: (4.0, 30.0, 3.0), 7: (9.0, 9.0, 9.0)})
    other = _episodes("case2", {0: (1.0, 22.0, 1.0), 1: (2.0, 33.0, 3.0)})
    table, seeds = example.compare({"base": base, "other": other})
    assert seeds == [0, 1]  # seed 7 was flown by one variant only
    rows = table.splitlines()
    assert rows[0].startswith("| case2, seeds 0 1 |")
    assert rows[2] == "| base | 3.00 ± 1.00 | 25.00 ± 5.00 | 2.00 ± 1.00 |"
    assert (
        rows[3]
        == "| other | 1.50 ± 0.50 (-50.0 %) | 27.50 ± 5.50 (+10.0 %) | 2.00 ± 1.00 (+0.0 %) |"
    )
    assert example.plot({"base": base, "other": other}, seeds, tmp_path / "c.png").is_file()
    with pytest.raises(ValueError, match="mix scenarios"):
        example.compare({"base": base, "c3": _episodes("case3", {0: (1.0, 1.0, 1.0)})})
    with pytest.raises(ValueError, match="share no seed"):
        example.compare({"base": base, "late": _episodes("case2", {5: (1.0, 1.0, 1.0)})})
    with pytest.raises(FileNotFoundError, match="no seed"):
        example.load_variant(tmp_path)


def test_episode_parity_counts_the_leading_steps_equal_to_the_bit():
    equal_steps = _load("episode_parity").equal_steps
    a = np.array([[1.0, np.nan], [2.0, 3.0], [4.0, 5.0]])
    b = a.copy()
    assert equal_steps(a, b) == 3  # NaN where both have NaN counts as equal
    b[1, 1] = np.nextafter(3.0, 4.0)  # one bit
    assert equal_steps(a, b) == 1
    b[0, 1] = 0.0
    assert equal_steps(a, b) == 0
    with pytest.raises(ValueError, match="shapes differ"):
        equal_steps(a, a[:2])
