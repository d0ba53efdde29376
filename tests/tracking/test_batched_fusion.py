"""The robust fusion runs on one batch of all of a step's measurements; here it is checked
against the same method written out per target and per measurement with 2 x 2 matrices
(:class:`PerMeasurementRobust`), over a seeded stream that takes every branch: births,
unseen targets, outliers rejected against the other drones (also of a pair, down to a last
survivor), a lagging track, a reset, non-finite measurements."""

import math
from collections import Counter

import numpy as np
import pytest

from dronefl.tracking import Fuser, FusionConfig, PositionMeasurement
from dronefl.tracking.adaptive import floor_eigenvalues
from dronefl.tracking.methods import (
    MAX_FADING,
    BatchUpdate,
    FusionMethod,
    MeasurementBatch,
    huber_second_moment,
)

DT = 0.2  # s
TARGETS = (3, 5, 8, 13)
DRONES = (2, 4, 6, 7, 9)
inv = np.linalg.inv


class PerMeasurementRobust(FusionMethod):
    """:class:`~dronefl.tracking.methods.RobustAdaptive` (see its class doc) one target at a
    time, every sum and leave-one-out mean over the drones written as a loop; ``events``
    counts the branches taken."""

    def __init__(self, config, n_drones, n_targets):
        super().__init__(config, n_drones, n_targets)
        r0 = config.initial_noise_std**2 * np.eye(2)
        self.r = np.tile(r0, (n_drones, n_targets, 1, 1))  # R_ij without the inflation
        phi = config.error_autocorrelation
        self.inflation = (1.0 + phi) / (1.0 - phi)
        self.events = Counter()

    def noise(self):
        return self.r * self.inflation

    def state(self):
        return self.r.copy()

    def restore(self, state):
        self.r = np.array(state, dtype=float)

    def update(self, batch, mean, covariance):
        mean, covariance = mean.copy(), covariance.copy()
        accepted = np.zeros(len(batch.target), dtype=bool)
        for g, j in enumerate(batch.targets):
            rows = batch.rows(g)
            mean[g], covariance[g], accepted[rows] = self.update_target(
                j, batch.drone[rows], mean[g], covariance[g], batch.position[rows]
            )
        return BatchUpdate(mean, covariance, accepted)

    def update_target(self, j, drones, x, p, z):
        config = self.config
        gate = math.inf if config.gate is None else config.gate
        r = [self.r[i, j] * self.inflation for i in drones]
        a = p[:2, :2]
        y = [zk - x[:2] for zk in z]
        prior_nis = [yk @ inv(a + rk) @ yk for yk, rk in zip(y, r, strict=True)]
        accepted, nis, residual, rest = [d <= gate for d in prior_nis], prior_nis, None, None
        if len(drones) >= 2 and config.consensus_gate is not None:
            accepted, nis, residual, rest = self.consensus(
                z, r, prior_nis, config.consensus_gate, gate
            )
        k2 = config.huber_threshold
        w = [
            (1.0 if d <= k2 else math.sqrt(k2 / d)) if ok else 0.0
            for d, ok in zip(nis, accepted, strict=True)
        ]
        if any(accepted):
            r_bar = inv(sum(wk * inv(rk) for wk, rk in zip(w, r, strict=True)))
            y_bar = r_bar @ sum(wk * inv(rk) @ yk for wk, rk, yk in zip(w, r, y, strict=True))
            fused_nis = y_bar @ inv(a + r_bar) @ y_bar
            if config.fading and fused_nis > gate:
                self.events["fading"] += 1
                p = p * min(fused_nis / gate, MAX_FADING)
                a = p[:2, :2]
            k = p[:, :2] @ inv(a + r_bar)
            i_kh = np.eye(len(x))
            i_kh[:, :2] -= k
            x = x + k @ y_bar
            p = i_kh @ p @ i_kh.T + k @ r_bar @ k.T
        if config.adaptive:
            self.adapt(j, drones, y, a, residual, rest, w, accepted)
        return x, p, accepted

    def consensus(self, z, r, prior_nis, gate, prior_gate):
        info = [inv(rk) for rk in r]
        alive = list(range(len(z)))
        accepted, nis = [False] * len(z), list(prior_nis)
        residual, rest = [None] * len(z), [None] * len(z)
        while len(alive) >= 2:
            d2 = {}
            for k in alive:
                others = [o for o in alive if o != k]
                rest[k] = inv(sum(info[o] for o in others))
                residual[k] = z[k] - rest[k] @ sum(info[o] @ z[o] for o in others)
                d2[k] = residual[k] @ inv(r[k] + rest[k]) @ residual[k]
            worst = max(alive, key=d2.get)  # the first of equals, in drone order
            if d2[worst] <= gate:
                for k in alive:
                    accepted[k], nis[k] = True, d2[k]
                return accepted, nis, residual, rest
            if len(alive) == 2:  # two that disagree: keep the one nearer the prior
                self.events["pair"] += 1
                worst = max(alive, key=lambda k: prior_nis[k])
            else:
                self.events["worst"] += 1
            nis[worst] = d2[worst]
            alive.remove(worst)
        self.events["last survivor"] += 1
        accepted[alive[0]] = prior_nis[alive[0]] <= prior_gate
        return accepted, nis, None, rest

    def adapt(self, j, drones, y, a, residual, rest, w, accepted):
        config = self.config
        used = [k for k, ok in enumerate(accepted) if ok]
        estimate = config.noise_estimate
        if residual is None or len(used) < 2:
            estimate = "innovation"
        gate = config.gate if estimate == "innovation" else config.consensus_gate
        c = huber_second_moment(config.huber_threshold, gate)
        for k in used:
            self.events[estimate] += 1
            if estimate == "innovation":
                outer, base = np.outer(y[k], y[k]), a
            elif estimate == "consensus":
                outer, base = np.outer(residual[k], residual[k]), rest[k]
            else:
                outer = 0.5 * (np.outer(y[k], residual[k]) + np.outer(residual[k], y[k]))
                base = np.zeros((2, 2))
            sample = (w[k] * outer / c - base) / self.inflation
            i = drones[k]
            blended = (1.0 - config.adaptation_rate) * self.r[
                i, j
            ] + config.adaptation_rate * sample
            self.r[i, j] = floor_eigenvalues(blended, config.noise_floor_std**2)


def _stream(seed=0, steps=100):
    """Every step's measurements ``(drone, target)``, shuffled: 4 targets at walking speed,
    5 drones each seeing each target 70 % of the time with its own bias and noise, 4 % of
    outliers; target 5 born at step 10, target 13 unseen for 8 steps, one drone wild on
    target 8 for 8 steps, target 8 jumping 6 m at step 60 (every track lags), target 3 seen
    50 m off by one drone only for 8 steps (a reset), 1 % of NaN positions."""
    rng = np.random.default_rng(seed)
    state = np.array([[0, 0, 0.5, 0.1], [20, 5, -0.4, 0], [-10, 15, 0, 0.6], [5, -20, 0.3, 0.3]])
    state = state.astype(float)
    bias = rng.normal(0.0, 0.3, (len(DRONES), len(TARGETS), 2))  # m
    std = rng.uniform(0.3, 1.5, (len(DRONES), len(TARGETS)))  # m
    stream = []
    for k in range(steps):
        state[:, :2] += DT * state[:, 2:]
        state[:, 2:] += rng.normal(0.0, 0.05, (len(TARGETS), 2))
        if k == 60:
            state[2, :2] += (6.0, 0.0)
        measurements = []
        for i, drone in enumerate(DRONES):
            for j, target in enumerate(TARGETS):
                hidden = (
                    (j == 1 and k < 10)
                    or (j == 3 and 30 <= k < 38)
                    or (j == 0 and 75 <= k < 83 and i != 0)
                )
                if hidden or rng.random() > 0.7:
                    continue
                z = state[j, :2] + bias[i, j] + std[i, j] * rng.normal(0.0, 1.0, 2)
                if rng.random() < 0.04:
                    z += rng.normal(0.0, 8.0, 2)
                if j == 2 and i == 4 and 40 <= k < 48:
                    z += (25.0, 0.0)
                if j == 0 and 75 <= k < 83:
                    z += (50.0, 0.0)
                if rng.random() < 0.01:
                    z[0] = np.nan
                measurements.append(PositionMeasurement(drone, target, z))
        rng.shuffle(measurements)
        stream.append(measurements)
    return stream


CONFIGS = {
    "default": FusionConfig(),
    "grubbs": FusionConfig(noise_estimate="grubbs"),
    "innovation": FusionConfig(noise_estimate="innovation"),
    "correlated": FusionConfig(error_autocorrelation=0.6, huber_threshold=4.0),
    "prior gate": FusionConfig(consensus_gate=None),
    "no gates": FusionConfig(gate=None, fading=False),
    "fixed R": FusionConfig(adaptive=False, reset_after=None),
}


@pytest.fixture(scope="module")
def stream():
    return _stream()


@pytest.mark.parametrize("name", CONFIGS)
def test_batched_robust_fusion_equals_the_per_measurement_method(stream, name):
    # Prepare: two Fusers on one stream, one with the reference method in place of its own.
    config = CONFIGS[name]
    batched = Fuser(TARGETS, DRONES, config)
    written_out = Fuser(TARGETS, DRONES, config)
    written_out.method = PerMeasurementRobust(config, len(DRONES), len(TARGETS))

    # Execute / Assert: the same tracks after every step, the same R and counters at the end.
    for k, measurements in enumerate(stream):
        ours = batched.update((k + 1) * DT, measurements)
        reference = written_out.update((k + 1) * DT, measurements)
        assert ours.keys() == reference.keys()
        for j, track in reference.items():
            assert (ours[j].accepted, ours[j].rejected) == (track.accepted, track.rejected)
            np.testing.assert_allclose(ours[j].mean, track.mean, rtol=1e-9, atol=1e-10)
            np.testing.assert_allclose(ours[j].covariance, track.covariance, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(batched.method.noise(), written_out.method.noise(), rtol=1e-9)
    counters = ("rejections", "measurements", "resets", "dropped")
    assert [getattr(batched, c) for c in counters] == [getattr(written_out, c) for c in counters]


def test_the_stream_takes_every_branch(stream):
    config = CONFIGS["default"]
    fuser = Fuser(TARGETS, DRONES, config)
    fuser.method = PerMeasurementRobust(config, len(DRONES), len(TARGETS))
    for k, measurements in enumerate(stream):
        fuser.update((k + 1) * DT, measurements)
    for event in ("fading", "pair", "worst", "last survivor", "innovation", "consensus"):
        assert fuser.method.events[event] > 0, event
    assert fuser.resets > 0 and fuser.dropped > 0


def test_a_batch_is_sorted_and_grouped_by_target_then_drone():
    batch = MeasurementBatch.of(
        target=np.array([2, 0, 2, 0, 5]),
        drone=np.array([1, 3, 0, 1, 2]),
        position=np.arange(10.0).reshape(5, 2),
    )
    np.testing.assert_array_equal(batch.target, [0, 0, 2, 2, 5])
    np.testing.assert_array_equal(batch.drone, [1, 3, 0, 1, 2])
    np.testing.assert_array_equal(batch.position[:, 0], [6.0, 2.0, 4.0, 0.0, 8.0])
    np.testing.assert_array_equal(batch.targets, [0, 2, 5])
    np.testing.assert_array_equal(batch.start, [0, 2, 4])
    np.testing.assert_array_equal(batch.count, [2, 2, 1])
    np.testing.assert_array_equal(batch.group, [0, 0, 1, 1, 2])
    assert batch.rows(1) == slice(2, 4)
    np.testing.assert_array_equal(batch.select(np.array([True, False, True])).target, [0, 0, 5])


def test_of_two_equally_far_drones_that_disagree_the_first_is_rejected():
    # Drones 1 and 2 report 4 m either side of the track with the same R: their residual
    # d^2 = 8^2 / 2 = 32 exceeds the consensus gate, and their innovations are exactly as far
    # from the prior, so the tie goes against the first in drone order; the second, a last
    # survivor, is within the prior's gate (16 / 2.04 < 9.21) and pulls the track to -x.
    fuser = Fuser([1], [1, 2], FusionConfig(), initial_positions={1: np.zeros(2)})
    track = fuser.update(
        DT,
        [
            PositionMeasurement(1, 1, np.array([4.0, 0.0])),
            PositionMeasurement(2, 1, np.array([-4.0, 0.0])),
        ],
    )[1]
    assert (track.accepted, track.rejected) == (1, 1)
    assert track.position[0] < -1.0
