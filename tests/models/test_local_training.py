"""Local training: FedProx's proximal term, determinism, learning, the MSE metric."""

import numpy as np
import pytest
import torch
from torch import nn

from dronefl.models.model import build_model, predictor_config
from dronefl.models.train import (
    TrainConfig,
    cut_detection_gaps,
    evaluate,
    proximal_term,
    train_local,
)
from dronefl.models.windows import BOX_DIM, FEATURE_DIM, WindowSpec, build_windows


def test_proximal_term_value_and_gradient():
    # Prepare: w = [1, 2], b = [0.5]; reference w_g = [0, 4], b_g = [0.5]; mu = 0.2.
    model = nn.Linear(2, 1)
    with torch.no_grad():
        model.weight.copy_(torch.tensor([[1.0, 2.0]]))
        model.bias.copy_(torch.tensor([0.5]))
    reference = {"weight": torch.tensor([[0.0, 4.0]]), "bias": torch.tensor([0.5])}
    term = proximal_term(reference, mu=0.2)
    # Execute
    value = term(model)
    value.backward()
    # Assert: (mu/2) ||w - w_g||^2 = 0.1 * (1 + 4) = 0.5; gradient mu (w - w_g) = [0.2, -0.4].
    assert value.item() == torch.tensor(0.5).item()
    torch.testing.assert_close(model.weight.grad, torch.tensor([[0.2, -0.4]]))
    torch.testing.assert_close(model.bias.grad, torch.tensor([0.0]))


def test_proximal_term_keeps_its_own_copy_of_the_reference():
    model = nn.Linear(1, 1, bias=False)
    reference = {"weight": model.weight.detach().clone()}
    term = proximal_term(reference, mu=1.0)
    reference["weight"].add_(10.0)  # changing the caller's dict afterwards has no effect
    assert term(model).item() == 0.0


def _windows(tiny_log):
    log, labels = tiny_log
    return build_windows(log, labels, WindowSpec(past_steps=3, future_steps=2))


def test_training_is_seeded_and_lowers_the_loss(tiny_log):
    data = _windows(tiny_log)
    config = predictor_config("dronefl", past_steps=3, future_steps=2)
    models = [build_model(config, seed=0) for _ in range(2)]
    before = evaluate(models[0], data)
    stats = [train_local(m, data, TrainConfig(epochs=20, batch_size=4, seed=7)) for m in models]
    after = evaluate(models[0], data)
    assert stats[0].loss == stats[1].loss
    for k, v in models[0].state_dict().items():
        torch.testing.assert_close(v, models[1].state_dict()[k])
    assert after < before


class _Zero(nn.Module):
    def forward(self, features: torch.Tensor, altitude: torch.Tensor) -> torch.Tensor:
        return torch.zeros(features.shape[0], 2, 2)


def test_evaluate_is_the_mean_squared_error_in_square_metres(tiny_log):
    data = _windows(tiny_log)
    # A model predicting the origin has MSE = mean of the squared labels.
    assert np.isclose(evaluate(_Zero(), data), np.mean(data.labels.astype(np.float64) ** 2))


def test_sgd_is_plain_sgd_with_momentum_and_unknown_optimisers_are_rejected():
    # Prepare: a 1-weight model fitting y = 0 from x = 1 with one window per step: loss w^2,
    # gradient 2 w. SGD with momentum 0.9 from w = 1, lr 0.1 (PyTorch's buffer starts at the
    # first gradient): v1 = 2, w1 = 0.8; v2 = 0.9 * 2 + 2 * 0.8 = 3.4, w2 = 0.8 - 0.34 = 0.46.
    class _Line(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.w = nn.Parameter(torch.ones(()))

        def forward(self, features: torch.Tensor, altitude: torch.Tensor) -> torch.Tensor:
            return self.w * features[:, :1, :2]

    class _Data:
        features = np.ones((1, 1, 2), np.float32)
        altitude = np.ones(1, np.float32)
        labels = np.zeros((1, 1, 2), np.float32)

        def __len__(self) -> int:
            return 1

    model = _Line()
    # Execute
    train_local(model, _Data(), TrainConfig(epochs=2, lr=0.1, batch_size=1, optimizer="sgd"))
    # Assert
    assert model.w.item() == pytest.approx(0.46, abs=1e-6)
    with pytest.raises(ValueError, match="optimizer"):
        TrainConfig(optimizer="lbfgs")


def _full_windows(batch: int, steps: int) -> torch.Tensor:
    """Windows detected at every step: boxes 1, odometry 2, the detected flag 1."""
    features = torch.full((batch, steps, FEATURE_DIM), 2.0)
    features[..., :BOX_DIM] = 1.0
    features[..., FEATURE_DIM - 1] = 1.0
    return features


def test_a_detection_gap_is_one_run_that_hides_boxes_and_flags_and_keeps_odometry():
    features = _full_windows(4000, 10)
    cut = cut_detection_gaps(features, 1.0, torch.Generator().manual_seed(0))
    hidden = cut[..., FEATURE_DIM - 1] == 0.0  # (B, L)
    # One run of 1..L-1 steps in every window, at every start, of every length.
    runs = (hidden[:, 1:] & ~hidden[:, :-1]).sum(1) + hidden[:, 0].long()
    assert (runs == 1).all()
    lengths = hidden.sum(1)
    assert set(lengths.tolist()) == set(range(1, 10))
    starts = hidden.float().argmax(1)
    assert set(starts.tolist()) == set(range(10))
    # The boxes go with the flag; the odometry stays; the input is not modified.
    assert (cut[..., :BOX_DIM][hidden] == 0.0).all() and (cut[..., :BOX_DIM][~hidden] == 1.0).all()
    assert (cut[..., BOX_DIM : FEATURE_DIM - 1] == 2.0).all()
    assert (features[..., FEATURE_DIM - 1] == 1.0).all()


def test_detection_gaps_take_a_window_s_share_and_never_its_last_detection():
    features = _full_windows(20_000, 10)
    cut = cut_detection_gaps(features, 0.3, torch.Generator().manual_seed(1))
    touched = (cut[..., FEATURE_DIM - 1] == 0.0).any(1).float().mean().item()
    assert touched == pytest.approx(0.3, abs=0.015)
    # A window detected at one step only keeps it; the gap can only hide it.
    single = torch.zeros(500, 10, FEATURE_DIM)
    single[:, 4, FEATURE_DIM - 1] = 1.0
    single[:, 4, :BOX_DIM] = 1.0
    kept = cut_detection_gaps(single, 1.0, torch.Generator().manual_seed(2))
    assert torch.equal(kept, single)
    # No gaps: the same tensor, and no draw from the generator.
    generator = torch.Generator().manual_seed(3)
    assert cut_detection_gaps(features, 0.0, generator) is features
    assert torch.equal(generator.get_state(), torch.Generator().manual_seed(3).get_state())
    with pytest.raises(ValueError, match="detection_gaps"):
        TrainConfig(detection_gaps=1.5)


def test_detection_gaps_change_the_training_and_are_seeded(tiny_log):
    data = _windows(tiny_log)
    config = predictor_config("dronefl", past_steps=3, future_steps=2)
    states = []
    for gaps in (0.0, 0.5, 0.5):
        model = build_model(config, seed=0)
        train_local(model, data, TrainConfig(epochs=3, batch_size=4, seed=7, detection_gaps=gaps))
        states.append(model.state_dict())
    for k in states[0]:
        torch.testing.assert_close(states[1][k], states[2][k], rtol=0, atol=0)
    assert any(not torch.equal(states[0][k], states[1][k]) for k in states[0])
