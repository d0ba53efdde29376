"""Each benchmark on tiny sizes: the figures exist, are finite and positive, and the references
are what they claim to be."""

import numpy as np
import pytest

from dronefl.bench.cloud import bench_cloud, filterpy_fusion, fly
from dronefl.bench.predictor import bench_inference, bench_training, record_windows
from dronefl.bench.simulator import bench_simulator
from dronefl.bench.vision import bench_detector, render_frames
from dronefl.config import load_scenario
from dronefl.tracking import Fuser, FusionConfig


def _positive(figure: dict) -> None:
    assert np.isfinite([figure["median"], figure["p95"]]).all()
    assert 0 < figure["median"] <= figure["p95"]


def test_filterpy_reference_is_our_fusion_without_adaptation_or_gating():
    pytest.importorskip("filterpy")
    scenario = load_scenario("case3")
    config = FusionConfig(adaptive=False, gate=None)
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

    figures = bench_inference(
        step, calls=3, rounds=1, measure_energy=lambda fn, n: readings.append(n) or {"joules": 1.0}
    )

    ours = figures["predictor_inference"]
    _positive(ours)
    _positive(figures["centralized_inference"])
    assert ours["threads"] == 1 and ours["targets"] == 6
    assert ours["ratio"] == pytest.approx(ours["reference"]["median"] / ours["median"])
    assert set(ours["other_runtimes"]) == {"torch", "torchscript"}
    assert ours["parameters"] < figures["centralized_inference"]["parameters"]
    assert readings == [3] and ours["energy_reading"] == {"joules": 1.0}


def test_training_figures_with_the_stock_reference(recorded):
    data, _ = recorded
    figures = bench_training(data, rounds=1)

    ours = figures["training_epoch"]
    _positive(ours)
    _positive(figures["centralized_training_epoch"])
    assert ours["windows"] == len(data) and ours["unit"] == "s"
    assert ours["ratio"] == pytest.approx(ours["reference"]["median"] / ours["median"])


def test_detector_on_rendered_case3_frames():
    scenario = load_scenario("case3")
    frames = render_frames(scenario, "crop_field", count=4, duration=2.0)

    assert [f.drone_id for f in frames] == [1, 2, 3, 4]
    assert {f.image.shape for f in frames} == {(640, 640, 3)}
    figures = bench_detector({"crop_field": frames}, scenario.target_ids)
    _positive(figures["detector"])
    _positive(figures["render"])
    assert figures["detector"]["samples"] == 4 and figures["detector"]["threads"] == 1
    assert set(figures["detector"]["per_environment"]) == {"crop_field"}


def test_simulator_reports_each_environment_and_the_slowest():
    scenario = load_scenario("case3")
    figure = bench_simulator(scenario, 2.0, ("crop_field", "orchard"))["simulator"]
    assert figure["min"] == min(figure["per_environment"].values()) > 0
