"""``FusionConfig.coverage_noise``: R scaled by how many of the last L updates carried the
pair's measurement (a drone predicting from a window with few detections errs more)."""

import json

import numpy as np
import pytest

from dronefl.tracking import Fuser, FusionConfig, PositionMeasurement
from dronefl.tracking.fusion import COVERAGE_NOISE_PROFILE, fusion_record

DT = 0.2  # s


def _stream(rng, n, profile, r, p_send):
    """``n`` updates of one still target at the origin seen by one drone that sends with
    probability ``p_send``: per update the measurement (or ``None``) and its true scale
    ``profile[k - 1]`` (``k`` its sends among the last ``len(profile)`` updates)."""
    sent, out = [], []
    for _ in range(n):
        sent.append(rng.random() < p_send)
        if not sent[-1]:
            out.append((None, 0.0))
            continue
        scale = profile[sum(sent[-len(profile) :]) - 1]
        out.append((rng.multivariate_normal(np.zeros(2), scale * r), scale))
    return out


def test_the_scale_counts_the_pairs_measurements_in_the_last_l_updates():
    fuser = Fuser([1], [1, 2], FusionConfig(coverage_noise=(4.0, 2.0, 1.0)), {1: np.zeros(2)})
    scales = []
    update = fuser.method.update

    def spy(batch, mean, covariance):
        scales.append(dict(zip((batch.drone + 1).tolist(), batch.scale.tolist(), strict=True)))
        return update(batch, mean, covariance)

    fuser.method.update = spy
    drone_2_sends = (True, False, True, True, True)
    for k, both in enumerate(drone_2_sends):
        drones = (1, 2) if both else (1,)
        fuser.update((k + 1) * DT, [PositionMeasurement(i, 1, np.zeros(2)) for i in drones])

    # Drone 1 sends every update: 1, 2, then 3 of the last 3. Drone 2 skips update 1.
    assert scales == [
        {1: 4.0, 2: 4.0},
        {1: 2.0},
        {1: 1.0, 2: 2.0},
        {1: 1.0, 2: 2.0},
        {1: 1.0, 2: 1.0},
    ]


def test_a_profile_of_ones_changes_nothing():
    rng = np.random.default_rng(3)
    stream = [
        [
            PositionMeasurement(i, 1, rng.normal(size=2))
            for i in (1, 2)
            if rng.random() < (0.9 if i == 1 else 0.5)
        ]
        for _ in range(400)
    ]
    fusers = [
        Fuser([1], [1, 2], FusionConfig(coverage_noise=coverage), {1: np.zeros(2)})
        for coverage in (None, (1.0,) * 10)
    ]
    for k, measurements in enumerate(stream):
        tracks = [fuser.update((k + 1) * DT, measurements) for fuser in fusers]
        np.testing.assert_array_equal(tracks[0][1].mean, tracks[1][1].mean)
        np.testing.assert_array_equal(tracks[0][1].covariance, tracks[1][1].covariance)
    np.testing.assert_array_equal(fusers[0].method.noise(), fusers[1].method.noise())


def test_the_adapted_r_is_that_of_a_full_window():
    # A drone whose error covariance is s(n) R, sending 80 % of the steps: with the profile the
    # adapted R is R (within 10 %), without it the R of the mixture, far larger.
    rng = np.random.default_rng(11)
    r = np.array([[0.3, 0.05], [0.05, 0.2]])
    stream = _stream(rng, 8000, COVERAGE_NOISE_PROFILE, r, p_send=0.8)
    estimates = {}
    for coverage in (COVERAGE_NOISE_PROFILE, None):
        config = FusionConfig(
            acceleration_psd=1e-6, initial_speed_std=1e-3, coverage_noise=coverage
        )
        fuser = Fuser([1], [1], config, {1: np.zeros(2)})
        kept = []
        for k, (z, _) in enumerate(stream):
            fuser.update((k + 1) * DT, [] if z is None else [PositionMeasurement(1, 1, z)])
            if k >= 4000:
                kept.append(fuser.measurement_noise(1, 1))
        estimates[coverage is not None] = np.mean(kept, axis=0)

    assert np.linalg.norm(estimates[True] - r) / np.linalg.norm(r) < 0.10
    assert np.trace(estimates[False]) > 1.5 * np.trace(r)


def test_down_weighting_sparse_windows_beats_one_r_per_pair():
    # Two drones on a random-walk target, errors s(n) R_i; one sends 95 % of the steps, the
    # other 70 %: knowing s(n) the fused track is better than with one adapted R per pair.
    rng = np.random.default_rng(5)
    n = 6000
    truth = np.cumsum(rng.normal(scale=0.2, size=(n, 2)), axis=0)  # m, ~1 m/s jumps each step
    noises = (np.diag([0.2, 0.2]), np.diag([0.3, 0.3]))
    streams = [
        _stream(rng, n, COVERAGE_NOISE_PROFILE, r, p)
        for r, p in zip(noises, (0.95, 0.7), strict=True)
    ]
    mse = {}
    for coverage in (COVERAGE_NOISE_PROFILE, None):
        fuser = Fuser([1], [1, 2], FusionConfig(acceleration_psd=1.0, coverage_noise=coverage))
        errors = []
        for k in range(n):
            measurements = [
                PositionMeasurement(i + 1, 1, truth[k] + streams[i][k][0])
                for i in range(2)
                if streams[i][k][0] is not None
            ]
            tracks = fuser.update((k + 1) * DT, measurements)
            if k >= 500 and 1 in tracks:
                errors.append(((tracks[1].position - truth[k]) ** 2).sum())
        mse[coverage is not None] = np.mean(errors)

    assert mse[True] < 0.9 * mse[False]


def test_coverage_noise_is_checked_and_recorded_only_when_set():
    with pytest.raises(ValueError, match="coverage_noise: must be positive"):
        FusionConfig(coverage_noise=(1.0, 0.0))
    with pytest.raises(ValueError, match="coverage_noise: must be positive"):
        FusionConfig(coverage_noise=())
    with pytest.raises(ValueError, match="coverage_noise: needs the robust"):
        FusionConfig(method="paper", coverage_noise=(2.0, 1.0))
    assert "coverage_noise" not in json.loads(fusion_record(FusionConfig()))
    config = FusionConfig(coverage_noise=[3, 1])  # as read back from JSON
    assert config.coverage_noise == (3.0, 1.0)
    assert FusionConfig(**json.loads(fusion_record(config))) == config
