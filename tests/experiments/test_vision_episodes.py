"""Every closed-loop method on the vision path (rendered frames, `--detector yolo`): a 10 s
episode each, with a model update at 5 s; the paper's image baseline (`centralized-image`)
states its input and size, sends only frames and odometry, and resumes bit-identically after a
kill."""

import json
import shutil
import signal

import numpy as np
import pytest
import torch

from dronefl.config import load_scenario
from dronefl.experiments.loop_checkpoint import CHECKPOINT_NAME, read_loop_checkpoint
from dronefl.experiments.pretrain import PretrainSpec
from dronefl.experiments.track import TRACK_METHODS, LoopParts, TrackConfig, run_episode
from dronefl.fl.checkpoint import Checkpoint, save_checkpoint
from dronefl.io import atomic_savez
from dronefl.models.image import FrameTransformer
from dronefl.models.model import build_model, count_parameters
from dronefl.perception import make_detector
from dronefl.settings import Setting

#: A model update at 5 s, every drone learning every label (Case 1: one drone per target),
#: labels from the truth: the freshly initialised image model's predictions are too far off
#: for the fusion to accept any, so there would be no fused track to label from.
OVERRIDES = ["learning.period=5", "learning.label_drones=all", "learning.labels=ground_truth"]
SETTING = Setting.load("recommended", OVERRIDES)
TRACK = ["track", "--scenario", "case1", "--method", "centralized-image", "--detector", "yolo",
         "--duration", "10", "--env", "crop_field", "--no-animate",
         *(a for o in OVERRIDES for a in ("--set", o))]  # fmt: skip


@pytest.fixture(scope="module")
def vision_pretrained(quick_pretrained, tmp_path_factory):
    """``quick_pretrained``'s DroneFL models beside a large box model and an image model, both
    freshly initialised (their accuracy is not under test: pretraining them is slow)."""
    folder = shutil.copytree(quick_pretrained, tmp_path_factory.mktemp("vision") / "pretrained")
    scenario = load_scenario("case1")
    large_spec = PretrainSpec(scenario, SETTING, "centralized")  # the quick choice: no gaps
    settings = large_spec.settings(folder)
    large = build_model(large_spec.model, seed=0)
    save_checkpoint(
        settings.checkpoint_path,
        settings.history_path,
        Checkpoint("centralized", settings.rounds, large.state_dict(), []),
    )
    image = PretrainSpec(scenario, SETTING, "image")
    torch.manual_seed(0)
    state = FrameTransformer(image.image_model).state_dict()
    atomic_savez(image.model_path(folder), **{k: v.numpy() for k, v in state.items()})
    return folder


@pytest.mark.slow
@pytest.mark.parametrize("method", TRACK_METHODS)
def test_every_method_flies_a_vision_episode(vision_pretrained, tmp_path, method):
    config = TrackConfig(
        scenario=load_scenario("case1"), setting=SETTING, method=method, detector="yolo",
        duration=10.0, environment="crop_field", runtime="torch",
        pretrained=vision_pretrained, out=tmp_path, progress=False, animate=False,
    )  # fmt: skip
    built = []

    def detector(name, world):
        built.append(make_detector(name, world))
        return built[-1]

    metrics = run_episode(config, LoopParts(detector=detector))

    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["detector"] == "yolo" and saved["method"] == method
    assert len(metrics.fl_rounds) == (0 if method == "fixed" else 1)
    assert metrics.tracking.prediction_coverage > 0.5
    comm = metrics.communication
    if method == "centralized-image":
        assert saved["model_input"] == "frames"
        assert saved["model_parameters"] == count_parameters(
            FrameTransformer(PretrainSpec(config.scenario, SETTING, "image").image_model)
        )
        assert "no detector" in metrics.centralized_inputs
    else:
        assert saved["model_input"] == "boxes"
        kind = "centralized" if method == "centralized" else "dronefl"
        model = PretrainSpec(config.scenario, SETTING, kind).model
        assert saved["model_parameters"] == count_parameters(build_model(model))
    if method.startswith("centralized"):
        # Per drone a 640x640 JPEG every 0.2 s (tens of kB) and 53 B of odometry up, the
        # controls down; no predictions travel (the cloud predicts).
        assert "JPEG" in metrics.centralized_inputs
        for drone in (1, 2):
            assert 20 * 5 < comm.kb_per_s(drone, "up", "frames") < 200 * 5  # KB/s at 5 Hz
            assert comm.kb_per_s(drone, "up", "odometry") == pytest.approx(53 * 5 / 1000)
            assert comm.kb_per_s(drone, "down", "control") == pytest.approx(14 * 5 / 1000)
        assert ("up", "predictions") not in comm.kinds()
    else:  # each drone detects on board and sends its predictions
        # The episode closed the detector's renderer, in its own thread (EGL refuses a context
        # freed from another one).
        assert [part.renderer for part in built] == [None]
        assert ("up", "frames") not in comm.kinds()
        assert comm.kb_per_s(kind="predictions") > 0


def test_the_image_baseline_needs_the_vision_path(vision_pretrained, tmp_path):
    with pytest.raises(ValueError, match="--method centralized-image.*--detector yolo"):
        TrackConfig(
            scenario=load_scenario("case1"), method="centralized-image", out=tmp_path,
            pretrained=vision_pretrained,
        )  # fmt: skip


def _outcome(out):
    metrics = json.loads((out / "metrics.json").read_text())
    for name in ("wall_seconds", "fl_seconds", "planner_ms_per_step"):
        metrics.pop(name)
    for entry in metrics["fl_rounds"]:
        entry.pop("seconds")
    metrics["config"].pop("out")
    with np.load(out / "episode.npz") as npz:
        episode = {k: npz[k] for k in npz.files}
    learner = read_loop_checkpoint(out / CHECKPOINT_NAME).learner
    return metrics, episode, learner


@pytest.mark.slow
def test_the_image_baseline_resumes_bit_identical(vision_pretrained, tmp_path, cli_process):
    def track(out, *args, crash_at=None):
        argv = [*TRACK, "--pretrained", str(vision_pretrained), "--out", str(out), *args]
        return cli_process(argv, crash_at)

    killed = tmp_path / "killed"
    # Killed writing the last checkpoint: the one after the update at 5 s (its frames and
    # retrained weights) is resumed from.
    kill = f"write:{CHECKPOINT_NAME}@2"
    assert track(killed, crash_at=kill) == -signal.SIGKILL
    assert read_loop_checkpoint(killed / CHECKPOINT_NAME).step == 25
    assert not (killed / "metrics.json").exists()
    assert track(killed, "--resume") == 0
    assert track(tmp_path / "reference") == 0

    metrics, episode, learner = _outcome(killed)
    ref_metrics, ref_episode, ref_learner = _outcome(tmp_path / "reference")
    assert metrics == ref_metrics
    assert episode.keys() == ref_episode.keys()
    for key in episode:
        np.testing.assert_array_equal(episode[key], ref_episode[key], err_msg=key)
    assert [f.shape for f in learner["frames"]] == [(50, 48, 48, 3)] * 2
    for a, b in zip(learner["frames"], ref_learner["frames"], strict=True):
        np.testing.assert_array_equal(a, b)
    for key, value in learner["model"].items():
        np.testing.assert_array_equal(value, ref_learner["model"][key])
