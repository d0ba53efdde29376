"""SCAFFOLD's drift correction: the correction term, the control variate's scale for PyTorch's
momentum SGD, the settings that refuse it, and a Flower run (killed after round 1 and resumed)
that equals the algorithm written out in-process."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from dronefl.fl.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from dronefl.fl.client_app import _windows
from dronefl.fl.records import CONTROL_KEY, FlSettings, SettingsError, WeightLayout, fl_settings
from dronefl.fl.simulation import run_federated
from dronefl.models.model import build_model
from dronefl.models.train import (
    SGD_MOMENTUM,
    TrainConfig,
    drift_correction,
    evaluate,
    local_steps,
    train_local,
    updated_control_variate,
)
from dronefl.settings import Setting


def test_the_correction_adds_c_minus_c_i_to_every_gradient():
    model = torch.nn.Linear(3, 2)
    server = {"weight": torch.full((2, 3), 0.5), "bias": torch.tensor([1.0, -1.0])}
    own = {"weight": torch.full((2, 3), 0.25), "bias": torch.tensor([3.0, 0.0])}
    term = drift_correction(server, own)
    term(model).backward()
    torch.testing.assert_close(model.weight.grad, torch.full((2, 3), 0.25))
    torch.testing.assert_close(model.bias.grad, torch.tensor([-2.0, -1.0]))


def test_the_control_variate_recovers_a_steady_gradient_under_momentum_sgd():
    # A loss with the constant gradient g: K steps of PyTorch's momentum SGD move w by
    # lr g (K - beta (1 - beta^K) / (1 - beta)) / (1 - beta), so the mean-gradient estimate
    # (1 - beta) (x - y) / (K lr) is g to within beta / ((1 - beta) K) = 0.9 % at K = 1000.
    g = torch.tensor([0.3, -2.0])
    w = torch.nn.Parameter(torch.zeros(2))
    optimiser = torch.optim.SGD([w], lr=1e-3, momentum=SGD_MOMENTUM)
    steps = 1000
    for _ in range(steps):
        optimiser.zero_grad()
        (w * g).sum().backward()
        optimiser.step()
    config = TrainConfig(lr=1e-3, optimizer="sgd")
    zero = {"w": torch.zeros(2)}
    estimate = updated_control_variate(zero, zero, {"w": torch.zeros(2)}, {"w": w}, steps, config)
    torch.testing.assert_close(estimate["w"], g, rtol=0.01, atol=0.0)
    # With earlier variates it is c_i - c plus the same estimate.
    shifted = updated_control_variate(
        {"w": torch.ones(2)}, {"w": torch.full((2,), 0.25)}, zero, {"w": w}, steps, config
    )
    torch.testing.assert_close(shifted["w"], estimate["w"] + 0.75)


def test_the_control_variate_refuses_adam():
    zero = {"w": torch.zeros(1)}
    with pytest.raises(ValueError, match="needs optimizer 'sgd'"):
        updated_control_variate(zero, zero, zero, zero, 1, TrainConfig(optimizer="adam"))


def test_settings_refuse_scaffold_with_adam_or_fedprox(tmp_path):
    with pytest.raises(SettingsError, match="drift-correction: 'scaffold' needs optimizer"):
        FlSettings("run", "out", drift_correction="scaffold")
    with pytest.raises(SettingsError, match="alternatives"):
        FlSettings("run", "out", method="fedprox", optimizer="sgd", drift_correction="scaffold")
    with pytest.raises(SettingsError, match="drift-correction: 'fedavgm' is not one of"):
        FlSettings("run", "out", drift_correction="fedavgm")
    setting = Setting.load("recommended")

    def trained(method: str) -> FlSettings:
        return fl_settings(
            setting, method, run_dir="run", out_dir="out", rounds=1, future_steps=5, stride=5,
            seed=0, field_m=(160.0, 120.0),
        )  # fmt: skip

    assert trained("dronefl").scaffold
    # Methods without FedAvg's local steps keep their own training.
    for method in ("fedprox", "centralized-small", "local"):
        assert not trained(method).scaffold


def test_the_control_variate_travels_beside_the_weights_and_is_checkpointed(tmp_path):
    state = {"a": torch.arange(6.0).reshape(2, 3), "b": torch.tensor([-1.0])}
    control = {"a": torch.full((2, 3), 0.5), "b": torch.tensor([2.0])}
    layout = WeightLayout.of(state)
    arrays = layout.pack(state, control)
    assert set(arrays) == {"weights", CONTROL_KEY}
    for k in state:
        torch.testing.assert_close(layout.unpack(arrays)[k], state[k])
        torch.testing.assert_close(layout.unpack_control(arrays)[k], control[k])
    with pytest.raises(SettingsError, match="no 'control' array"):
        layout.unpack_control(layout.pack(state))
    paths = tmp_path / "checkpoint.npz", tmp_path / "history.json"
    save_checkpoint(*paths, Checkpoint("dronefl", 3, state, [], control))
    loaded = load_checkpoint(*paths, "dronefl", like=state)
    torch.testing.assert_close(loaded.control["b"], control["b"])
    save_checkpoint(*paths, Checkpoint("dronefl", 3, state, []))
    assert load_checkpoint(*paths, "dronefl", like=state).control is None


def _reference(settings: FlSettings, rounds: int, correct: bool = True) -> list[dict[int, float]]:
    """SCAFFOLD (option II) written out: per round, every drone steps along g_i - c_i + c
    from the global model, c_i <- c_i - c + (1 - beta)(x - y_i) / (K lr), and the cloud takes
    the sample-weighted means of the y_i and the c_i (without ``correct``: plain FedAvg);
    returns each round's test MSE per drone."""
    drones = [1, 2]
    x = build_model(settings.model, seed=settings.seed).state_dict()
    zeros = {k: torch.zeros_like(v) for k, v in x.items()}
    c, own = zeros, {d: zeros for d in drones}
    out = []
    for r in range(1, rounds + 1):
        models, counts, variates = {}, {}, {}
        for d in drones:
            train_set, _ = _windows(settings.run_dir, d, settings.windows, settings.labels)
            model = build_model(settings.model, seed=settings.seed)
            model.load_state_dict(x)
            config = settings.train_config(r, d)
            train_local(model, train_set, config, drift_correction(c, own[d]) if correct else None)
            y = model.state_dict()
            steps = local_steps(len(train_set), config)
            variates[d] = updated_control_variate(own[d], c, x, y, steps, config)
            models[d], counts[d] = y, len(train_set)
        total = sum(counts.values())
        x = {k: sum(counts[d] * models[d][k] for d in drones) / total for k in x}
        c = {k: sum(counts[d] * variates[d][k] for d in drones) / total for k in x}
        own = variates
        model = build_model(settings.model, seed=settings.seed)
        model.load_state_dict(x)
        out.append(
            {
                d: evaluate(
                    model, _windows(settings.run_dir, d, settings.windows, settings.labels)[1]
                )
                for d in drones
            }
        )
    return out


@pytest.mark.slow
def test_scaffold_through_flower_equals_the_algorithm_and_resumes(case1_run, tmp_path):
    settings = fl_settings(
        Setting.load("recommended", ["training.epochs=2"]), "dronefl", run_dir=str(case1_run),
        out_dir=str(tmp_path), rounds=1, future_steps=5, stride=5, seed=0,
        field_m=(160.0, 120.0),
    )  # fmt: skip
    assert settings.scaffold and settings.optimizer == "sgd"
    run_federated(settings)  # round 1, then the engine stops: a fresh context on resume
    history = run_federated(replace(settings, rounds=2, resume=True))
    expected = _reference(settings, 2)
    for entry, reference in zip(history, expected, strict=True):
        assert entry.rejected == ()
        for drone, mse in reference.items():
            np.testing.assert_allclose(entry.test_mse[drone], mse, rtol=1e-4)
    # Plain FedAvg from the same start: round 1 is the same (c = c_i = 0), round 2 is not.
    plain = _reference(settings, 2, correct=False)
    for drone in (1, 2):
        np.testing.assert_allclose(plain[0][drone], expected[0][drone], rtol=1e-6)
        assert abs(plain[1][drone] - expected[1][drone]) > 1e-3 * expected[1][drone]
    # The control variate travels beside the weights in training (two fp32 vectors per drone
    # and round), not to evaluation.
    weights_bytes = 2 * settings.layout.size * 4
    assert 2 * weights_bytes < history[1].bytes_up["train"] < 2.1 * weights_bytes
    assert weights_bytes < history[1].bytes_down["evaluate"] < 1.1 * weights_bytes
    # Each drone keeps its last two control variates on its disk.
    kept = sorted(p.name for p in (tmp_path / "control").iterdir())
    assert kept == [f"drone_{d}_round_{r}.npz" for d in (1, 2) for r in (1, 2)]
