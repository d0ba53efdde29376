"""Pretraining: a cache keyed by content, run outside any FL session, and a failure inside
Flower that ends the command quickly, in one line, with no Ray process left behind."""

import json
import os
import shutil
import subprocess
import sys
import time
import uuid
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from dronefl.config import load_scenario, parse_scenario
from dronefl.experiments import pretrain as pretrain_module
from dronefl.experiments.pretrain import PretrainSpec, held_out_mse, pretrain, pretrained_state
from dronefl.experiments.simulate import simulate
from dronefl.fl.checkpoint import Checkpoint, save_checkpoint
from dronefl.fl.records import RoundRecord
from dronefl.models.model import build_model
from dronefl.settings import Setting

SCENARIO = load_scenario("case1")


def _spec(kind: str = "dronefl", *overrides: str, setting: str = "recommended") -> PretrainSpec:
    """Case 1's pretraining of ``kind`` as the named setting with ``overrides`` says."""
    return PretrainSpec(SCENARIO, Setting.load(setting, overrides), kind)


def test_editing_the_scenario_changes_the_cache_key(tmp_path):
    spec = _spec()
    raw = {
        "name": "case1",
        "targets": [{"id": 1, "lane": 2, "start_x": 30.0}, {"id": 2, "lane": 20, "start_x": 130.0}],
        "drones": [{"id": 1, "altitude": 30.0, "targets": [1]},
                   {"id": 2, "altitude": 20.0, "targets": [2]}],
    }  # fmt: skip
    edited = replace(spec, scenario=parse_scenario(raw))
    faster = replace(spec, scenario=parse_scenario(_with_speed(raw, 0.6)))

    paths = {s.settings(tmp_path).checkpoint_path for s in (spec, edited, faster)}
    assert len(paths) == 3  # same name, three contents, three cache entries
    assert spec.settings(tmp_path).checkpoint_path == spec.settings(tmp_path).checkpoint_path


def test_every_training_setting_is_in_the_cache_key(tmp_path):
    spec = _spec()
    variants = [
        spec,
        _spec("dronefl", "model.past_steps=8"),
        _spec("dronefl", "pretraining.stride=3"),
        _spec("dronefl", "pretraining.rounds=5"),
        _spec("dronefl", "training.lr=1e-3"),
        _spec("dronefl", "model.box_size=image"),
        replace(spec, kind="centralized"),
        replace(spec, detection_gaps=0.3),
        _spec("dronefl", "pretraining.seconds=300"),
        replace(spec, recording_seed=7),
    ]
    assert len({v.settings(tmp_path).out_dir for v in variants}) == len(variants)
    # The recording is shared by the two kinds and by every training setting.
    assert {v.settings(tmp_path).run_dir for v in variants[:8]} == {spec.settings(tmp_path).run_dir}
    # What the setting says of the fusion, the planner or the online rounds is not.
    others = ("fusion.temporal_kernel=false", "planner.distance_at=next", "learning.epochs=3")
    assert _spec("dronefl", *others).settings(tmp_path) == spec.settings(tmp_path)
    assert variants[7].settings(tmp_path).detection_gaps == 0.3
    with pytest.raises(ValueError, match="detection_gaps"):
        replace(spec, detection_gaps=2.0)


def test_changed_code_changes_the_cache_key(tmp_path, monkeypatch):
    import dronefl.experiments.pretrain as pretrain

    package = tmp_path / "package"
    (package / "sim").mkdir(parents=True)
    (package / "sim" / "world.py").write_text("STEP = 0.2\n")
    (package / "sim" / "notes.txt").write_text("not code")
    (package / "config.py").write_text("")
    before = pretrain.code_digest(("sim", "config.py"), package)
    (package / "sim" / "notes.txt").write_text("edited, still not code")
    assert pretrain.code_digest(("sim", "config.py"), package) == before
    (package / "sim" / "world.py").write_text("STEP = 0.1\n")
    assert pretrain.code_digest(("sim", "config.py"), package) != before
    with pytest.raises(FileNotFoundError, match="missing"):
        pretrain.code_digest(("sim", "gone.py"), package)

    # Recording code keys the recording and the model; training code the model alone.
    spec = _spec()
    first = spec.settings(tmp_path)
    digest = pretrain.package_digest
    monkeypatch.setattr(
        pretrain, "package_digest", lambda parts: digest(parts) + ("x" if "fl" in parts else "")
    )
    retrained = spec.settings(tmp_path)
    assert retrained.run_dir == first.run_dir and retrained.out_dir != first.out_dir
    monkeypatch.setattr(
        pretrain, "package_digest", lambda parts: digest(parts) + ("x" if "sim" in parts else "")
    )
    recorded = spec.settings(tmp_path)
    assert recorded.run_dir != first.run_dir and recorded.out_dir != first.out_dir


def _with_speed(raw: dict, speed: float) -> dict:
    return {**raw, "targets": [{**t, "speed": speed} for t in raw["targets"]]}


def _processes_tagged(tag: str) -> list[int]:
    """PIDs of live processes whose environment holds ``tag`` (the command's whole tree:
    Ray's workers inherit the environment)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if tag.encode() in (entry / "environ").read_bytes():
                found.append(int(entry.name))
        except OSError:
            continue
    return found


@pytest.mark.slow
def test_a_client_app_failing_in_pretraining_ends_the_command(tmp_path):
    # Prepare: the crop-field recording pretraining would make, with every drone's log corrupt,
    # so that each ClientApp raises inside the Flower simulation.
    spec = _spec("dronefl", "pretraining.rounds=2", "pretraining.seconds=10",
                 "pretraining.detection_gaps=0")  # fmt: skip
    data = Path(spec.settings(tmp_path).run_dir)
    simulate(SCENARIO, environment="crop_field", duration=10.0, seed=spec.recording_seed,
             out=data, progress=False, plot=False)  # fmt: skip
    for log in data.glob("drone_*.npz"):
        log.write_bytes(b"not a log")
    tag = f"DRONEFL_TEST_{uuid.uuid4().hex}"
    env = {**os.environ, tag: "1", "FLWR_TELEMETRY_ENABLED": "0", "MPLBACKEND": "Agg"}
    command = [sys.executable, "-m", "dronefl.cli", "pretrain", "--scenario", "case1",
               "--set", "pretraining.rounds=2", "--set", "pretraining.seconds=10",
               "--set", "pretraining.detection_gaps=0", "--out", str(tmp_path)]  # fmt: skip

    # Execute (a run that hung on the failed round would meet the timeout, and fail the test)
    result = subprocess.run(command, env=env, capture_output=True, text=True, timeout=180)

    # Assert: non-zero exit, one line naming what failed, nothing left running.
    assert result.returncode != 0
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("error: ") and "corrupt log file" in last, last
    assert str(data / "drone_") in last  # it names the file the ClientApp could not read
    deadline = time.monotonic() + 10
    while _processes_tagged(tag) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert _processes_tagged(tag) == []


def test_the_setting_sets_what_is_pretrained(tmp_path):
    ours, paper = _spec(), _spec(setting="paper")
    trained = ours.settings(tmp_path)
    assert (trained.optimizer, trained.lr, trained.batch_size) == ("sgd", 3e-4, 64)
    assert (trained.epochs, trained.rounds, trained.stride, trained.future_steps) == (10, 20, 2, 1)
    assert ours.model.box_size == "metric" and paper.model.box_size == "image"
    assert paper.settings(tmp_path).optimizer == "adam"
    assert replace(ours, kind="centralized").model.d_model == 64  # the large model, same options
    assert trained.out_dir != paper.settings(tmp_path).out_dir
    assert trained.run_dir == paper.settings(tmp_path).run_dir  # one recording for both
    with pytest.raises(ValueError, match="kind"):
        PretrainSpec(SCENARIO, Setting.load(), "bogus")


def test_held_out_mse_reads_the_last_evaluated_round(tmp_path):
    spec = _spec("dronefl", "pretraining.rounds=2")
    settings = spec.settings(tmp_path)
    state = build_model(spec.model).state_dict()
    history = [RoundRecord(1, {1: 4.0, 2: 3.0}), RoundRecord(2, {2: 0.5, 1: 1.5})]
    save_checkpoint(
        settings.checkpoint_path, settings.history_path, Checkpoint("dronefl", 2, state, history)
    )
    assert held_out_mse(spec, tmp_path) == {1: 1.5, 2: 0.5}

    save_checkpoint(
        settings.checkpoint_path,
        settings.history_path,
        Checkpoint("dronefl", 2, state, [RoundRecord(1), RoundRecord(2)]),
    )
    with pytest.raises(ValueError, match="no evaluated round"):
        held_out_mse(spec, tmp_path)


def test_the_image_model_is_pretrained_on_rendered_frames_once(tmp_path):
    spec = _spec("image", "pretraining.seconds=8")
    first = pretrain(spec, tmp_path, progress=False)

    path = spec.model_path(tmp_path)
    assert path.parent.name.startswith("image-") and path.is_file()
    assert (spec.data_dir(tmp_path) / "frames_48px_q90.npz").is_file()  # rendered once, kept
    report = json.loads((path.parent / "pretrain.json").read_text())
    assert report["model_input"] == "frames" and report["parameters"] > 100_000
    assert len(report["train_loss"]) == 30
    per_drone = held_out_mse(spec, tmp_path)
    assert sorted(per_drone) == [1, 2] and all(v > 0 for v in per_drone.values())
    # Cached: the same weights, nothing trained again.
    written = path.stat().st_mtime_ns
    again = pretrained_state(spec, tmp_path, progress=False)
    assert path.stat().st_mtime_ns == written
    assert all(torch.equal(first[k], again[k]) for k in first)
    # Its own key: a DroneFL model of the same recording lives elsewhere; the image model's
    # settings and training code are in its key, the drones' training is not (it trains as it
    # says).
    dronefl = replace(spec, kind="dronefl").settings(tmp_path).checkpoint_path.parent
    assert spec.image_dir(tmp_path) != dronefl and dronefl.parent == spec.image_dir(tmp_path).parent
    eight = _spec("image", "pretraining.seconds=8", "model.past_steps=8")
    assert eight.image_dir(tmp_path) != spec.image_dir(tmp_path)
    adam = _spec("image", "pretraining.seconds=8", "training.lr=1e-3")
    assert adam.image_dir(tmp_path) == spec.image_dir(tmp_path)


def test_a_stopped_pretraining_goes_on_from_its_checkpoint(tmp_path, monkeypatch):
    spec = _spec("centralized", "pretraining.rounds=2", "pretraining.seconds=30")
    whole = pretrain(spec, tmp_path / "whole", progress=False)
    # What a pretraining stopped after its first round (Ctrl-C, a kill) leaves behind: the
    # recording and round 1's checkpoint.
    settings = spec.settings(tmp_path / "stopped")
    shutil.copytree(spec.settings(tmp_path / "whole").run_dir, settings.run_dir)
    pretrain_module.run_centralized(replace(settings, rounds=1))
    played: list[int] = []
    real = pretrain_module.run_centralized

    def spy(settings, on_round):
        return real(settings, on_round=lambda e: (played.append(e.server_round), on_round(e)))

    monkeypatch.setattr(pretrain_module, "run_centralized", spy)
    resumed = pretrain(spec, tmp_path / "stopped", progress=False)

    assert played == [2]  # round 1 was not trained again
    assert resumed.keys() == whole.keys()
    assert all(torch.equal(resumed[k], whole[k]) for k in whole)  # as if never stopped
