"""The transformer: AdaIN statistics, attention against PyTorch's, variants, masking."""

import numpy as np
import pytest
import torch
from torch import nn

from dronefl.models.model import (
    AltitudeAdaIN,
    Attention,
    PredictorConfig,
    _LastDimSoftmax,
    build_model,
    count_parameters,
    metric_box,
    predictor_config,
)
from dronefl.models.windows import (
    ALTITUDE_SCALE_M,
    FEATURE_DIM,
    PositionFrame,
    window_features,
)


def test_adain_output_has_the_styles_mean_and_std():
    # Prepare: style (mu, sigma) = A h/50 + b with A = [1, 2 | 3, 4], b = [0.5, -1 | 0.2, 2].
    adain = AltitudeAdaIN(channels=2)
    with torch.no_grad():
        adain.style.weight.copy_(torch.tensor([[1.0], [2.0], [3.0], [4.0]]))
        adain.style.bias.copy_(torch.tensor([0.5, -1.0, 0.2, 2.0]))
    z = torch.randn(3, 10, 2) * 5 + 7  # (B, T, C)
    altitude = torch.tensor([25.0, 50.0, 100.0])  # m -> h = 0.5, 1, 2
    # Execute
    out = adain(z, altitude)
    # Assert: per instance and channel, mean over time = mu, std over time = |sigma|.
    h = (altitude / 50.0)[:, None]
    mu = torch.cat([1.0 * h + 0.5, 2.0 * h - 1.0], dim=1)  # (B, C)
    sigma = torch.cat([3.0 * h + 0.2, 4.0 * h + 2.0], dim=1)
    torch.testing.assert_close(out.mean(dim=1), mu, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out.std(dim=1, unbiased=False), sigma.abs(), atol=1e-3, rtol=1e-3)


@pytest.mark.parametrize(("axis", "dim"), [("time", 1), ("channel", 2)])
def test_identity_style_is_the_plain_normalisation(axis, dim):
    # A = 0, b = (mu, sigma) = (0, 1): o = (z - mean(z)) / std(z), whatever the altitude.
    adain = AltitudeAdaIN(channels=3, axis=axis, init="identity", eps=0.0)
    z = torch.tensor([[[1.0, 2.0, 6.0], [3.0, 4.0, 0.0]]])  # (B=1, T=2, C=3)
    expected = (z - z.mean(dim=dim, keepdim=True)) / z.std(dim=dim, unbiased=False, keepdim=True)
    for altitude in (20.0, 60.0):
        torch.testing.assert_close(adain(z, torch.tensor([altitude])), expected)


def test_channel_adain_by_hand():
    # z = (1, 3) over C = 2 channels: mean 2, std 1, so z_hat = (-1, 1). Altitude 100 m ->
    # h = 2; A = (0, 0 | 1, 2), b = (0.5, -0.5 | 0, 1) -> mu = (0.5, -0.5), sigma = (2, 5).
    adain = AltitudeAdaIN(channels=2, axis="channel", eps=0.0)
    with torch.no_grad():
        adain.style.weight.copy_(torch.tensor([[0.0], [0.0], [1.0], [2.0]]))
        adain.style.bias.copy_(torch.tensor([0.5, -0.5, 0.0, 1.0]))
    out = adain(torch.tensor([[[1.0, 3.0]]]), torch.tensor([100.0]))
    # o = sigma * z_hat + mu = (2 * -1 + 0.5, 5 * 1 - 0.5)
    torch.testing.assert_close(out, torch.tensor([[[-1.5, 4.5]]]))


def test_sigma_follows_a_h_plus_b_and_the_altitude_init_is_proportional_to_h():
    # sigma = A h + b: with A = 0.5, b = 0.25 the output std is 0.5 * h/50 + 0.25.
    adain = AltitudeAdaIN(channels=1, axis="time", eps=0.0)
    with torch.no_grad():
        adain.style.weight.copy_(torch.tensor([[0.0], [0.5]]))
        adain.style.bias.copy_(torch.tensor([0.0, 0.25]))
    z = torch.tensor([[[0.0], [2.0]]]).expand(3, 2, 1)  # z_hat = (-1, 1) in every instance
    altitude = torch.tensor([25.0, 50.0, 100.0])  # h/50 = 0.5, 1, 2
    out = adain(z, altitude)
    torch.testing.assert_close(out[:, 1, 0], torch.tensor([0.5, 0.75, 1.25]))
    # The "altitude" start: mu = 0, sigma = h / 50 m, so the output doubles with the altitude.
    physical = AltitudeAdaIN(channels=4, axis="channel", init="altitude")
    z = torch.randn(2, 3, 4)
    torch.testing.assert_close(
        physical(z, torch.full((2,), 60.0)), 2 * physical(z, torch.full((2,), 30.0))
    )


def test_adain_needs_more_than_one_step():
    with pytest.raises(ValueError, match="at least 2 time steps"):
        AltitudeAdaIN(4)(torch.zeros(2, 1, 4), torch.ones(2))


def test_attention_matches_torch_multihead_attention():
    torch.manual_seed(0)
    ours = Attention(d_model=16, n_heads=4, dropout=0.0).eval()
    ref = nn.MultiheadAttention(16, 4, batch_first=True).eval()
    with torch.no_grad():
        ref.in_proj_weight.copy_(ours.in_proj.weight)
        ref.in_proj_bias.copy_(ours.in_proj.bias)
        ref.out_proj.weight.copy_(ours.out_proj.weight)
        ref.out_proj.bias.copy_(ours.out_proj.bias)
    x, memory = torch.randn(5, 3, 16), torch.randn(5, 10, 16)
    torch.testing.assert_close(ours(x), ref(x, x, x, need_weights=False)[0])
    torch.testing.assert_close(ours(x, memory), ref(x, memory, memory, need_weights=False)[0])


def test_softmax_gradient_is_exact():
    a = torch.randn(2, 3, 4, 5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(_LastDimSoftmax.apply, (a,))
    torch.testing.assert_close(_LastDimSoftmax.apply(a), a.softmax(-1))


@pytest.mark.parametrize("variant", ["dronefl", "plain", "large"])
def test_every_variant_predicts_lf_positions(variant):
    model = build_model(predictor_config(variant, past_steps=10, future_steps=5)).eval()
    out = model(torch.randn(7, 10, FEATURE_DIM), torch.full((7,), 30.0))
    assert out.shape == (7, 5, 2)
    assert torch.isfinite(out).all()


def test_variants_differ_as_specified():
    dronefl, plain, large = (predictor_config(v) for v in ("dronefl", "plain", "large"))
    assert (dronefl.adain, dronefl.relative) == (True, True)
    assert (plain.adain, plain.relative) == (False, False)
    assert (dronefl.d_model, dronefl.n_heads, dronefl.d_ff) == (16, 4, 32)
    assert large.d_model == 64
    n = {v: count_parameters(build_model(predictor_config(v))) for v in ("dronefl", "plain")}
    # AdaIN adds A (16 x 2) and b (32) = 64 parameters per site: 2 encoder layers + the head.
    assert n["dronefl"] - n["plain"] == 3 * 64
    encoder_only = build_model(predictor_config("dronefl", adain_sites=("encoder",)))
    assert count_parameters(encoder_only) - n["plain"] == 2 * 64


def test_lf_of_one_works_with_encoder_and_head_adain():
    model = build_model(PredictorConfig(past_steps=10, future_steps=1)).eval()
    assert model.head_adain is not None and len(model.adain) == 2
    assert model(torch.randn(2, 10, FEATURE_DIM), torch.tensor([20.0, 40.0])).shape == (2, 1, 2)


def test_missed_detections_do_not_change_the_prediction():
    rng = np.random.default_rng(1)
    odometry = rng.normal(size=(10, 12))
    detected = np.array([True] * 5 + [False] * 5)
    boxes = rng.uniform(size=(10, 4))
    junk = boxes.copy()
    junk[~detected] = rng.uniform(size=(5, 4))  # different garbage where the target was missed
    model = build_model(predictor_config("dronefl")).eval()
    h = torch.tensor([30.0])
    outs = [
        model(
            torch.from_numpy(window_features(b, detected, odometry, np.zeros(2), PositionFrame()))[
                None
            ],
            h,
        )
        for b in (boxes, junk)
    ]
    torch.testing.assert_close(outs[0], outs[1])


def test_metric_box_sizes_by_hand():
    # A 4 m vehicle under an 80 deg camera: footprint 2 h tan(40 deg) m, so the box width is
    # 4 / footprint(h) of the image and w * 10 * h / 50 m is the same at 20 m and at 60 m.
    footprint = 2 * np.tan(np.radians(40.0))
    rows = []
    for h in (20.0, 60.0):
        boxes = np.tile([0.6, 0.4, 4.0 / (footprint * h), 2.0 / (footprint * h)], (3, 1))
        odometry = np.zeros((3, 12))
        odometry[:, 2] = h
        detected = np.array([True, True, False])
        rows.append(window_features(boxes, detected, odometry, np.zeros(2), PositionFrame()))
    image = torch.from_numpy(np.stack(rows))  # (2 altitudes, 3 steps, F)
    metric = metric_box(image)
    expected = 10 * np.array([4.0, 2.0]) / (footprint * ALTITUDE_SCALE_M)
    for k in range(2):
        np.testing.assert_allclose(metric[k, :2, 2:4].numpy(), np.tile(expected, (2, 1)), rtol=1e-6)
    assert image[0, 0, 2] == pytest.approx(3 * image[1, 0, 2])  # in image units: 3x apart
    assert torch.equal(metric[:, 2], image[:, 2])  # a missed step stays all zero
    untouched = [k for k in range(FEATURE_DIM) if k not in (2, 3)]
    assert torch.equal(metric[..., untouched], image[..., untouched])


def test_ground_boxes_read_a_ground_offset_the_same_at_every_altitude():
    # A target 6 m east and 3 m north of the point below a nadir camera with an 80 deg field:
    # its box centre sits 6 / (footprint(h) / 2) of the half image from the centre, so
    # 2 (cx - 0.5) * h / 50 m is the same at 20 m and at 60 m, and so is the 4 m x 2 m box.
    footprint = 2 * np.tan(np.radians(40.0))
    rows = []
    for h in (20.0, 60.0):
        half = footprint * h / 2
        box = [
            0.5 + 6.0 / half / 2,
            0.5 + 3.0 / half / 2,
            4.0 / (footprint * h),
            2.0 / (footprint * h),
        ]
        odometry = np.zeros((2, 12))
        odometry[:, 2] = h
        detected = np.array([True, False])
        rows.append(
            window_features(np.tile(box, (2, 1)), detected, odometry, np.zeros(2), PositionFrame())
        )
    image = torch.from_numpy(np.stack(rows))  # (2 altitudes, 2 steps, F)
    ground = metric_box(image, "ground")
    torch.testing.assert_close(ground[0, 0, :4], ground[1, 0, :4])
    expected = np.array([6.0, 3.0]) / (footprint * ALTITUDE_SCALE_M / 2)
    np.testing.assert_allclose(ground[0, 0, :2].numpy(), expected, rtol=1e-6)
    assert image[0, 0, 0] == pytest.approx(3 * image[1, 0, 0])  # in image units: 3x apart
    torch.testing.assert_close(ground[..., 2:4], metric_box(image)[..., 2:4])
    assert torch.equal(ground[:, 1], image[:, 1])  # a missed step stays all zero
    assert torch.equal(ground[..., 4:], image[..., 4:])


def test_a_metric_model_is_an_image_model_fed_metric_sizes():
    metric = build_model(predictor_config("dronefl", box_size="metric"), seed=2).eval()
    image = build_model(predictor_config("dronefl"), seed=2).eval()
    x, h = torch.rand(5, 10, FEATURE_DIM), torch.full((5,), 40.0)
    torch.testing.assert_close(metric(x, h), image(metric_box(x), h))
    assert not torch.allclose(metric(x, h), image(x, h))
    with pytest.raises(ValueError, match="box_size"):
        PredictorConfig(box_size="pixels")


def test_same_seed_same_weights():
    a = build_model(predictor_config("dronefl"), seed=3).state_dict()
    b = build_model(predictor_config("dronefl"), seed=3).state_dict()
    c = build_model(predictor_config("dronefl"), seed=4).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)


def test_bad_shapes_and_configs_are_rejected():
    model = build_model(predictor_config("dronefl"))
    with pytest.raises(ValueError, match="features must have shape"):
        model(torch.zeros(2, 9, FEATURE_DIM), torch.ones(2))
    with pytest.raises(ValueError, match="multiple of n_heads"):
        PredictorConfig(d_model=10, n_heads=4)
    with pytest.raises(ValueError, match="unknown predictor variant"):
        predictor_config("huge")
    with pytest.raises(ValueError, match="adain_sites"):
        PredictorConfig(adain_sites=("decoder",))
