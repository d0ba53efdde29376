"""``FusionConfig.temporal_kernel``: the position a Fuser outputs is a short kernel over the
drones' last fused predictions; the filter's state and history stay as without it."""

from pathlib import Path

import numpy as np
import pytest

from dronefl.config import load_scenario
from dronefl.experiments.replay import Episode, fit_temporal_kernel
from dronefl.io import load_state, save_state
from dronefl.tracking import Fuser, FusionConfig, PositionMeasurement
from dronefl.tracking.fusion import TEMPORAL_KERNEL

DT = 0.2  # s
LAG_KERNEL = (1.5, -0.5)  # undoes a prediction half a step behind a constant-velocity target


VELOCITY = np.array([0.8, -0.3])  # m/s


def _lagging(n, velocity=VELOCITY):
    """A target at constant ``velocity`` (m/s) and a prediction of each step's position half a
    step behind it: ``truth`` / ``prediction`` ``(n, 2)`` m."""
    truth = np.arange(1, n + 1)[:, None] * DT * velocity
    return truth, truth - 0.5 * DT * velocity


def test_the_kernel_undoes_a_lag_and_leaves_the_filter_alone():
    truth, prediction = _lagging(60)
    fusers = {
        kernel: Fuser([1], [1, 2], FusionConfig(temporal_kernel=kernel), {1: np.zeros(2)})
        for kernel in (LAG_KERNEL, None)
    }
    for k in range(60):
        measurements = [PositionMeasurement(i, 1, prediction[k]) for i in (1, 2)]
        tracks = {kernel: f.update((k + 1) * DT, measurements)[1] for kernel, f in fusers.items()}
        if k >= 1:  # two updates in: every lag exists
            np.testing.assert_allclose(tracks[LAG_KERNEL].position, truth[k], atol=1e-12)
            forecast = fusers[LAG_KERNEL].forecast(DT)
            np.testing.assert_array_equal(forecast.positions[0], tracks[LAG_KERNEL].position)
        np.testing.assert_array_equal(tracks[LAG_KERNEL].covariance, tracks[None].covariance)
    # The filter itself lags (its state is the one without the kernel), the output does not.
    assert np.linalg.norm(tracks[None].position - truth[-1]) > 0.01
    with_kernel, without = (fusers[k].history(1) for k in (LAG_KERNEL, None))
    np.testing.assert_array_equal(with_kernel.mean, without.mean)


def test_a_drone_without_every_lag_is_left_out_and_none_falls_back_to_the_filter():
    truth, prediction = _lagging(12)
    fuser = Fuser([1], [1, 2], FusionConfig(temporal_kernel=LAG_KERNEL), {1: np.zeros(2)})
    plain = Fuser([1], [1, 2], FusionConfig(), {1: np.zeros(2)})
    far = np.array([50.0, 50.0])  # drone 2's single prediction: gated out, never in the kernel
    for k in range(12):
        measurements = [PositionMeasurement(1, 1, prediction[k])] if k != 5 else []
        if k == 8:
            measurements.append(PositionMeasurement(2, 1, prediction[k] + far))
        track = fuser.update((k + 1) * DT, measurements)[1]
        reference = plain.update((k + 1) * DT, measurements)[1]
        if k in (5, 6):  # drone 1 skipped update 5: no drone has both lags at 5 and 6
            np.testing.assert_array_equal(track.position, reference.position)
        elif k >= 1:
            np.testing.assert_allclose(track.position, truth[k], atol=1e-12)
    assert fuser.rejections == 1


def test_the_drones_are_weighted_by_their_r():
    # One tap: the output is the information-weighted mean of the step's two predictions.
    config = FusionConfig(temporal_kernel=(1.0,), adaptive=False)
    fuser = Fuser([1], [1, 2], config, {1: np.zeros(2)})
    noise = (np.diag([0.1, 0.4]), np.diag([0.3, 0.1]))
    for i, r in enumerate(noise):
        fuser.method._r[:, i, 0] = (r[0, 0], r[0, 1], r[1, 1])
    z = (np.array([0.2, -0.1]), np.array([-0.3, 0.2]))
    track = fuser.update(DT, [PositionMeasurement(i + 1, 1, z[i]) for i in range(2)])[1]

    info = [np.linalg.inv(r) for r in noise]
    expected = np.linalg.solve(info[0] + info[1], info[0] @ z[0] + info[1] @ z[1])
    np.testing.assert_allclose(track.position, expected, atol=1e-12)


def test_fit_temporal_kernel_finds_the_kernel_that_undoes_the_lag():
    scenario = load_scenario("case2")
    n, m, t = 400, len(scenario.drone_ids), len(scenario.target_ids)
    rng = np.random.default_rng(2)
    velocity = rng.normal(size=(t, 2))
    truth = np.arange(n + 1)[:, None, None] * DT * velocity  # (n + 1, N, 2) m
    prediction = np.broadcast_to(truth[1:, None] - 0.5 * DT * velocity, (n, m, t, 2)).copy()
    prediction[rng.random((n, m, t)) < 0.2] = np.nan  # gaps: those steps need other drones
    episode = Episode(
        path=Path("synthetic"),
        scenario=scenario,
        prediction=prediction,
        target_position=truth,
        track_position=truth,
        t=np.arange(n + 1) * DT,
    )

    np.testing.assert_allclose(fit_temporal_kernel([episode], 2), LAG_KERNEL, atol=1e-9)
    three = fit_temporal_kernel([episode], 3)
    assert sum(three) == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(ValueError, match="too few"):
        fit_temporal_kernel([episode], 200)


def test_the_kernel_is_checked():
    with pytest.raises(ValueError, match="temporal_kernel: the weights must sum to 1"):
        FusionConfig(temporal_kernel=(1.0, 0.5))
    with pytest.raises(ValueError, match="temporal_kernel: must be finite"):
        FusionConfig(temporal_kernel=())
    assert sum(TEMPORAL_KERNEL) == pytest.approx(1.0, abs=1e-12)
    config = FusionConfig(method="paper", temporal_kernel=list(TEMPORAL_KERNEL))  # from JSON
    assert config.temporal_kernel == TEMPORAL_KERNEL


def test_a_restored_fuser_goes_on_with_its_kernel_as_if_never_stopped(tmp_path):
    truth, prediction = _lagging(30)
    config = FusionConfig(temporal_kernel=TEMPORAL_KERNEL)
    fuser = Fuser([1], [1, 2], config, {1: np.zeros(2)})

    def step(f, k):
        drones = (1, 2) if k % 7 else (1,)  # drone 2 skips every 7th update
        return f.update((k + 1) * DT, [PositionMeasurement(i, 1, prediction[k]) for i in drones])

    for k in range(12):
        step(fuser, k)
    save_state(tmp_path / "fuser.npz", fuser.state())
    copy = Fuser([1], [1, 2], config, {1: np.zeros(2)})
    copy.restore(load_state(tmp_path / "fuser.npz"))
    for k in range(12, 30):
        a, b = step(fuser, k)[1], step(copy, k)[1]
        np.testing.assert_array_equal(a.mean, b.mean)
        np.testing.assert_array_equal(a.covariance, b.covariance)
