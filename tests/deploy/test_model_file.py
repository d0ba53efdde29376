"""A deployment's model file carries its architecture: the drones build the predictor the file
holds, and a setting that changes the model without changing its weights' shapes (``metric``
box sizes) can never be flown with another setting's reading."""

import numpy as np
import pytest
import torch

from dronefl.deploy.clientapp import load_model, save_model
from dronefl.deploy.drone import load_predictor
from dronefl.deploy.processes import DeployError
from dronefl.fl.records import online_settings
from dronefl.models.model import PredictorConfig, build_model, predictor_config
from dronefl.settings import Setting


def _model(name: str, *overrides: str) -> PredictorConfig:
    return online_settings(Setting.load(name, overrides), "dronefl", 0, (160.0, 120.0)).model


def test_predictor_config_round_trips_through_json():
    config = _model("recommended")
    assert config.box_size == "metric"
    assert PredictorConfig.from_json(config.to_json()) == config
    with pytest.raises(ValueError, match="unknown fields"):
        PredictorConfig.from_json('{"d_model": 16, "colour": "red"}')
    with pytest.raises(ValueError, match="box_size"):
        PredictorConfig.from_json('{"box_size": "huge"}')
    with pytest.raises(ValueError, match="not JSON"):
        PredictorConfig.from_json("{")


def test_model_file_round_trips_weights_round_and_architecture(tmp_path):
    config = _model("recommended")
    state = build_model(config, seed=3).state_dict()
    save_model(tmp_path / "m.npz", state, 7, config)
    saved = load_model(tmp_path / "m.npz")
    assert saved.server_round == 7 and saved.model == config
    assert saved.state.keys() == state.keys()
    assert all(torch.equal(saved.state[k], state[k]) for k in state)


def test_the_drone_flies_the_architecture_in_the_file(tmp_path):
    ours, metric = _model("recommended", "model.box_size=image"), _model("recommended")
    # The two settings' models have the same weights, so only the file can tell them apart.
    assert ours != metric
    state = build_model(metric, seed=0).state_dict()
    assert {k: v.shape for k, v in state.items()} == {
        k: v.shape for k, v in build_model(ours).state_dict().items()
    }
    save_model(tmp_path / "m.npz", state, 0, metric)
    assert load_predictor(tmp_path / "m.npz", past_steps=10).config == metric
    save_model(tmp_path / "m20.npz", build_model(ours).state_dict(), 0, ours)
    with pytest.raises(DeployError, match="L_p = 10"):
        load_predictor(tmp_path / "m20.npz", past_steps=20)


def test_a_file_without_an_architecture_record_is_refused(tmp_path):
    config = predictor_config("dronefl", 10, 1)
    state = build_model(config).state_dict()
    np.savez(
        tmp_path / "old.npz",
        __server_round__=np.array(0),
        **{k: v.numpy() for k, v in state.items()},
    )
    with pytest.raises(FileNotFoundError, match="old.npz: missing or corrupt model file"):
        load_model(tmp_path / "old.npz")
