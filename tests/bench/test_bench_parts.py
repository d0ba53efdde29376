"""Each benchmark on tiny sizes: each figure holds exactly the samples asked for, its timed
calls fit in the wall time the benchmark took (a unit or sample-count error breaks that bound),
and the references are what they claim to be."""

from time import perf_counter

import numpy as np
import pytest

from dronefl.bench.cloud import bench_cloud, filterpy_fusion, fly
from dronefl.bench.energy import EnergyReading
from dronefl.bench.predictor import bench_inference, bench_training, record_windows
from dronefl.bench.results import BenchFigure
from dronefl.bench.simulator import bench_simulator
from dronefl.bench.timing import UNITS
from dronefl.bench.vision import bench_detector, render_frames
from dronefl.config import load_scenario
from dronefl.tracking import Fuser, FusionConfig


def _measured(figure: BenchFigure, samples: int, elapsed: float) -> None:
    """``figure`` summarises ``samples`` timings that all happened within ``elapsed`` s: at
    least half of them last the median or longer, so (samples / 2) x median <= elapsed."""
    assert figure.samples == samples
    median_s = figure.median * UNITS[figure.unit]
    assert median_s > 0 and samples / 2 * median_s <= elapsed
    assert figure.median <= figure.p95


def test_filterpy_reference_is_our_fusion_without_adaptation_or_gating():
    pytest.importorskip("filterpy")
    scenario = load_scenario("case3")
    # The robust method with every robust part off (no gates, no Huber down-weighting, no
    # fading) is a plain Kalman filter: its joint update equals filterpy's sequential ones.
    config = FusionConfig(
        adaptive=False, gate=None, consensus_gate=None, fading=False, huber_threshold=1e12
    )
    _, _, stream = fly(scenario, steps=30, config=config)

    _, reference = filterpy_fusion(stream, scenario.dt, config)
    fuser = Fuser(scenario.target_ids, scenario.drone_ids, config)
    for k, measurements in enumerate(stream):
        tracks = fuser.update((k + 1) * scenario.dt, measurements)

    assert set(reference) == set(tracks)
    for j, state in reference.items():
        np.testing.assert_allclose(tracks[j].mean, state, rtol=0, atol=1e-9)


def test_cloud_needs_more_steps_than_its_warmup():
    with pytest.raises(ValueError, match="steps"):
        bench_cloud(load_scenario("case3"), steps=5)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    folder = tmp_path_factory.mktemp("record")
    return record_windows(load_scenario("case3"), folder, duration=20.0, per_target=5)


def test_recorded_windows_and_step_have_drone_1s_six_targets(recorded):
    data, step = recorded
    assert set(np.unique(data.target_ids)) == {1, 2, 3, 4, 5, 6} and len(data) == 30
    assert step["odometry"].shape == (10, 12) and step["boxes"].shape == (10, 6, 4)
    assert step["detected"].any(axis=0).all()  # the chosen step sees every target


def test_inference_figures_with_the_stock_reference(recorded):
    _, step = recorded
    readings = []
    reading = EnergyReading("reading", 1.0, 6, 5.0, "a fake meter")

    started = perf_counter()
    figures = bench_inference(
        step, calls=3, rounds=2, measure_energy=lambda fn, n: readings.append(n) or reading
    )
    elapsed = perf_counter() - started

    ours = figures.predictor_inference
    for figure in (ours, ours.reference, figures.centralized_inference):
        _measured(figure, samples=6, elapsed=elapsed)
    assert ours.threads == 1 and ours.targets == 6
    # ONNX Runtime runs the step faster than the stock eager build (README: 3.2x).
    assert ours.ratio > 1
    assert set(ours.other_runtimes) == {"torch", "torchscript"}
    assert ours.parameters < figures.centralized_inference.parameters
    assert readings == [6] and ours.energy_reading == reading


def test_training_figures_with_the_stock_reference(recorded):
    data, _ = recorded
    started = perf_counter()
    figures = bench_training(data, rounds=2)
    elapsed = perf_counter() - started

    ours = figures.training_epoch
    for figure in (ours, ours.reference, figures.centralized_training_epoch):
        _measured(figure, samples=2, elapsed=elapsed)
    assert ours.windows == len(data) == 30 and ours.unit == "s"
    # (No claim on the ratio here: on 30 windows an epoch lasts milliseconds, and on a shared
    # machine two samples of that are noise; the README's 1.33x is from 3000 windows.)


def test_detector_on_rendered_case3_frames():
    scenario = load_scenario("case3")
    frames = render_frames(scenario, "crop_field", count=4, duration=2.0)

    assert [f.drone_id for f in frames] == [1, 2, 3, 4]
    assert {f.image.shape for f in frames} == {(640, 640, 3)}
    started = perf_counter()
    figures = bench_detector({"crop_field": frames}, scenario.target_ids)
    _measured(figures.detector, samples=4, elapsed=perf_counter() - started)
    # Rendering was timed while the frames were made: each frame's own render time.
    renders = sorted(f.render_seconds for f in frames)
    assert figures.render.median == pytest.approx(1e3 * np.median(renders))
    assert figures.detector.samples == 4 and figures.detector.threads == 1
    assert set(figures.detector.per_environment) == {"crop_field"}


def test_simulator_reports_each_environment_and_the_slowest():
    scenario = load_scenario("case3")
    figure = bench_simulator(scenario, 2.0, ("crop_field", "orchard")).simulator
    assert figure.min == min(figure.per_environment.values()) > 0
