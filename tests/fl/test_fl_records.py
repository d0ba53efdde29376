"""The records adapter and checkpoints: round trips and clear errors."""

from dataclasses import replace

import numpy as np
import pytest
import torch
from flwr.app import ConfigRecord

from dronefl.fl.checkpoint import Checkpoint, CheckpointError, load_checkpoint, save_checkpoint
from dronefl.fl.records import (
    ClientReport,
    FlSettings,
    RoundRecord,
    SettingsError,
    TrainInstructions,
    WeightLayout,
    fl_settings,
    online_settings,
    to_arrays,
    to_state,
)
from dronefl.settings import Setting


def test_settings_survive_the_run_config():
    settings = FlSettings("runs/x", "out/y", method="fedprox", rounds=7, proximal_mu=0.5)
    config = settings.to_run_config()
    assert config["run-dir"] == "runs/x" and config["proximal-mu"] == 0.5
    assert FlSettings.from_run_config(config) == settings


@pytest.mark.parametrize(
    ("config", "message"),
    [
        ({"out-dir": "o"}, "missing key 'run-dir'"),
        ({"run-dir": "r", "out-dir": "o", "rounds": "5"}, "'rounds' must be int"),
        ({"run-dir": "r", "out-dir": "o", "method": "fedsgd"}, "unknown 'fedsgd'"),
        ({"run-dir": "r", "out-dir": "o", "epochs": 0}, "epochs: must be >= 1"),
    ],
)
def test_bad_run_config_names_the_key(config, message):
    with pytest.raises(SettingsError, match=message):
        FlSettings.from_run_config(config)


def test_model_weights_and_reports_round_trip():
    state = {"a": torch.arange(6.0).reshape(2, 3), "b": torch.tensor([1.5])}
    back = to_state(to_arrays(state))
    assert all(torch.equal(state[k], back[k]) for k in state)
    report = ClientReport(drone_id=3, num_examples=40, value=0.25)
    assert ClientReport.from_metrics(report.to_metrics()) == report
    instructions = TrainInstructions.from_config(
        ConfigRecord({"server-round": 4, "proximal-mu": 0.1})
    )
    assert instructions == TrainInstructions(4, 0.1)
    assert TrainInstructions.from_config(ConfigRecord({"server-round": 2})).proximal_mu == 0.0


@pytest.mark.parametrize(("dtype", "tolerance"), [("float32", 0.0), ("float16", 2.0**-11)])
def test_weights_travel_as_one_flat_vector(dtype, tolerance):
    state = {"a": torch.randn(3, 4, generator=torch.Generator().manual_seed(0)), "b": torch.ones(2)}
    layout = WeightLayout.of(state, dtype)
    arrays = layout.pack(state)
    assert list(arrays.keys()) == ["weights"] and arrays["weights"].shape == (14,)
    assert arrays["weights"].dtype == dtype
    back = layout.unpack(arrays)
    for k, v in state.items():
        assert back[k].dtype == torch.float32 and back[k].shape == v.shape
        torch.testing.assert_close(back[k], v, rtol=tolerance, atol=0.0)
    other = WeightLayout.of({"a": torch.zeros(15)})
    with pytest.raises(SettingsError, match="expected 14 values"):
        layout.unpack(other.pack({"a": torch.zeros(15)}))
    with pytest.raises(SettingsError, match="weights-dtype"):
        FlSettings("r", "o", weights_dtype="int8")


def test_checkpoint_round_trip_and_damage(tmp_path):
    path, history_path = tmp_path / "checkpoint.npz", tmp_path / "history.json"
    state = {"w": torch.tensor([1.0, 2.0])}
    history = [RoundRecord(1, {1: 3.0}, {1: 4.0}), RoundRecord(2, {1: 2.0}, {1: 2.5}, ("x",))]
    save_checkpoint(path, history_path, Checkpoint("dronefl", 2, state, history))

    back = load_checkpoint(path, history_path, "dronefl")
    assert back.server_round == 2 and back.history == history
    torch.testing.assert_close(back.state["w"], state["w"])
    assert back.history[1].mean_test_mse == 2.0 and back.history[1].rejected == ("x",)
    with pytest.raises(CheckpointError, match="not 'fedavg'"):
        load_checkpoint(path, history_path, "fedavg")
    path.write_bytes(path.read_bytes()[:40])
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        load_checkpoint(path, history_path, "dronefl")
    with pytest.raises(CheckpointError, match="no checkpoint"):
        load_checkpoint(tmp_path / "none.npz", history_path, "dronefl")


def test_non_finite_checkpoint_is_refused(tmp_path):
    path, history_path = tmp_path / "c.npz", tmp_path / "h.json"
    save_checkpoint(path, history_path, Checkpoint("fedavg", 1, {"w": torch.tensor([np.nan])}, []))
    with pytest.raises(CheckpointError, match="non-finite"):
        load_checkpoint(path, history_path, "fedavg")


def test_round_records_survive_json_and_name_a_bad_field():
    record = RoundRecord(3, {1: 0.5, 2: 1.5}, {1: 0.2, 2: 0.4}, ("drone 2: x",),
                         {"train": 10, "evaluate": 4}, {"train": 12})  # fmt: skip
    entry = record.to_json()
    assert entry["mean_test_mse"] == 1.0 and entry["test_mse"] == {"1": 0.5, "2": 1.5}
    assert RoundRecord.from_json(entry) == record
    assert RoundRecord(1).mean_test_mse is None  # no evaluation in that round
    with pytest.raises(SettingsError, match="round history entry"):
        RoundRecord.from_json({"round": 1})


def _trained(name: str, method: str = "dronefl", rounds: int = 50, *overrides: str):
    setting = Setting.load(name, overrides)
    return fl_settings(
        setting, method, run_dir="r", out_dir="o", rounds=rounds, future_steps=5, stride=10,
        seed=0, field_m=(160.0, 120.0),
    )  # fmt: skip


def test_a_setting_sets_the_training_and_the_adain_placement():
    paper = _trained("paper")
    assert (paper.epochs, paper.lr, paper.optimizer) == (10, 1e-3, "adam")
    assert paper.model.adain_sites == ("encoder",)
    assert (paper.model.box_size, paper.batch_size) == ("image", 128)
    ours = _trained("recommended")
    assert (ours.model.box_size, ours.batch_size, ours.lr) == ("metric", 64, 3e-4)
    assert ours.train_config(1, 1).optimizer == "sgd" and ours.drift_correction == "scaffold"
    # The FL baselines read boxes as the paper's do, whatever the setting; SCAFFOLD corrects
    # FedAvg-based federated methods only.
    assert replace(ours, method="fedavg").model.box_size == "image"
    assert _trained("recommended", "fedprox").drift_correction == "none"
    assert _trained("recommended", "local").drift_correction == "none"
    with pytest.raises(SettingsError, match="optimizer"):
        FlSettings("r", "o", optimizer="rmsprop")
    with pytest.raises(SettingsError, match="box_size"):
        FlSettings("r", "o", box_size="pixels")
    with pytest.raises(SettingsError, match="adain_sites"):
        FlSettings("r", "o", adain_sites="decoder")


def test_the_stepped_lr_drops_tenfold_in_the_last_fifth_of_the_rounds():
    step = _trained("recommended", "dronefl", 50, "training.lr_step_at=0.8")
    assert [step.train_config(r, 1).lr for r in (1, 40)] == [3e-4, 3e-4]
    assert [step.train_config(r, 2).lr for r in (41, 50)] == pytest.approx([3e-5, 3e-5])
    # Pretraining's 20 rounds step after round 16; every method of the setting steps alike.
    assert replace(step, rounds=20).lr_of(16) == 3e-4
    assert replace(step, rounds=20).lr_of(17) == pytest.approx(3e-5)
    local = _trained("recommended", "local", 50, "training.lr_step_at=0.8")
    assert local.lr_of(50) == pytest.approx(3e-5) and local.drift_correction == "none"
    assert step.training_key()["lr_step_at"] == 0.8
    assert FlSettings.from_run_config(step.to_run_config()) == step
    with pytest.raises(SettingsError, match="lr-step-at: must be in"):
        FlSettings("r", "o", lr_step_at=0.0)


def test_the_closed_loop_trains_every_online_round_at_one_lr():
    setting = Setting.load("recommended", ["training.lr_step_at=0.8"])
    settings = online_settings(setting, "dronefl", 0, (160.0, 120.0))
    assert settings.lr_step_at == 1.0 and settings.lr_of(settings.rounds + 1) == 3e-4
    assert (settings.epochs, settings.future_steps, settings.stride) == (1, 1, 2)
    assert (settings.labels, settings.train_fraction) == ("tracks", 1.0)


def test_detection_gaps_reach_local_training_and_key_only_the_runs_that_cut_them():
    plain = _trained("recommended")
    gaps = replace(plain, detection_gaps=0.3)
    assert plain.train_config(1, 1).detection_gaps == 0.0
    assert gaps.train_config(4, 2).detection_gaps == 0.3
    assert plain.training_key()["detection_gaps"] == 0.0
    assert gaps.training_key()["detection_gaps"] == 0.3
    assert FlSettings.from_run_config(gaps.to_run_config()) == gaps
    with pytest.raises(SettingsError, match="detection-gaps: must be in"):
        FlSettings("r", "o", detection_gaps=-0.1)
