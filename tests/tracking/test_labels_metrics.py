"""Pseudo-label sources (smoothed, filtered, ground truth) on the episode grid, the pull
estimate and the labels' de-shrinking, and OSPA/GOSPA from Stone Soup checked by hand."""

import math

import numpy as np
import pytest

from dronefl.tracking import (
    LABEL_SOURCES,
    Fuser,
    FusionConfig,
    PositionMeasurement,
    make_labels,
    set_distances,
)
from dronefl.tracking.labels import deshrink_labels, drone_labels, estimate_pull, label_drones

DT = 0.2  # s


def _fly(n_steps=100, unseen=range(40, 90)):
    """Target 1 drives east at 1 m/s, seen by drone 1 (0.3 m noise) except during ``unseen``
    steps; target 2 is never seen. Updates at (k + 1) dt, as in the closed loop."""
    rng = np.random.default_rng(1)
    fuser = Fuser([1, 2], [1], FusionConfig(method="paper", adaptive=False))
    truth = np.zeros((n_steps + 1, 2, 2))
    truth[:, 0, 0] = np.arange(n_steps + 1) * DT
    for k in range(n_steps):
        ms = []
        if k not in unseen:
            ms.append(PositionMeasurement(1, 1, truth[k + 1, 0] + rng.normal(0, 0.3, 2)))
        fuser.update((k + 1) * DT, ms)
    return fuser, truth, np.arange(n_steps + 1) * DT


def test_labels_sit_on_the_episode_grid():
    fuser, truth, t = _fly()
    filtered = make_labels("filtered", fuser, t, max_std=1e6)
    history = fuser.history(1)
    assert np.isnan(filtered.position[0]).all()  # the track is born at t = dt
    np.testing.assert_array_equal(filtered.position[1:, 0], history.mean[:, :2])
    assert np.isnan(filtered.position[:, 1]).all()  # nobody saw target 2
    truth_labels = make_labels("ground_truth", fuser, t, truth=truth)
    np.testing.assert_array_equal(truth_labels.position, truth)
    np.testing.assert_array_equal(truth_labels.variance, 0.0)
    with pytest.raises(ValueError, match="truth of shape"):
        make_labels("ground_truth", fuser, t)
    with pytest.raises(ValueError, match="unknown source"):
        make_labels("tracks", fuser, t)
    assert set(LABEL_SOURCES) == {"smoothed", "filtered", "ground_truth"}


def test_smoothed_labels_are_better_and_uncertain_ones_are_dropped():
    fuser, truth, t = _fly()
    smoothed = make_labels("smoothed", fuser, t, max_std=0.5)
    filtered = make_labels("filtered", fuser, t, max_std=0.5)
    seen = slice(5, 40)

    def mse(labels):
        return np.nanmean(((labels.position[seen, 0] - truth[seen, 0]) ** 2).sum(-1))

    assert mse(smoothed) < 0.8 * mse(filtered)
    # In the long gap the filtered std grows past 0.5 m and those labels are dropped; the
    # smoother, which sees both ends of the gap, keeps more of them.
    gap = slice(42, 91)
    assert np.isnan(filtered.position[gap, 0, 0]).sum() > 20
    assert (
        np.isnan(smoothed.position[gap, 0, 0]).sum() < np.isnan(filtered.position[gap, 0, 0]).sum()
    )
    kept = np.isfinite(smoothed.position[..., 0])
    assert (smoothed.variance[kept] <= 0.25 + 1e-12).all()
    assert smoothed.kept == pytest.approx(kept.mean())


def test_ospa_and_gospa_by_hand():
    truth = np.array([[[0.0, 0.0], [20.0, 0.0]]] * 3)  # (3 steps, 2 targets, 2)
    tracks = truth.copy()
    tracks[:, 0, 0] += 1.0  # target 1 tracked 1 m off
    tracks[:, 1] = np.nan  # target 2 has no track
    m = set_distances(truth, tracks, DT, cutoff=10.0, order=2.0)
    # OSPA: ((1^2 + 10^2) / 2)^(1/2); GOSPA (alpha = 2): (1^2 + 10^2 / 2)^(1/2).
    assert m.ospa == pytest.approx(math.sqrt(50.5), rel=1e-12)
    assert m.gospa == pytest.approx(math.sqrt(51.0), rel=1e-12)
    assert m.gospa_localisation == pytest.approx(1.0, rel=1e-12)
    assert m.gospa_missed == pytest.approx(50.0, rel=1e-12)
    assert m.gospa_false == 0.0
    perfect = set_distances(truth, truth, DT)
    assert perfect.ospa == 0.0 and perfect.gospa == 0.0
    with pytest.raises(ValueError, match="order"):
        set_distances(truth, tracks, DT, order=0.5)
    with pytest.raises(ValueError, match=r"\(K, N, 2\)"):
        set_distances(truth[:, :1], tracks, DT)


def test_label_drones_by_rule():
    # Step 0: drones 1 (60 m) and 2 (40 m) see target 1; step 1: drone 1 alone; drone 3 (20 m)
    # sees target 2 at both steps.
    predicted = np.zeros((2, 3, 2), dtype=bool)
    predicted[0, :2, 0] = True
    predicted[1, 0, 0] = True
    predicted[:, 2, 1] = True
    altitudes = [60.0, 40.0, 20.0]
    assert label_drones(predicted, altitudes, "all").all()
    others = label_drones(predicted, altitudes, "others")
    assert others[:, :, 0].tolist() == [[True, False], [True, False], [False, False]]
    assert not others[:, :, 1].any()  # drone 3 alone sees target 2
    lower = label_drones(predicted, altitudes, "lower")
    assert lower[:, :, 0].tolist() == [[True, False], [False, False], [False, False]]
    assert not lower[:, :, 1].any()
    # Drones that withhold undetected predictions (--detected-only): a drone watching the
    # target learns the steps another drone's prediction reached the cloud, its own or not.
    assigned = np.array([[True, False], [True, False], [True, True]])
    watched = label_drones(predicted, altitudes, "others", assigned)
    assert watched[:, :, 0].tolist() == [[True, False], [True, True], [True, True]]
    assert not watched[:, :, 1].any()
    with pytest.raises(ValueError, match="assigned"):
        label_drones(predicted, altitudes, "others", assigned[:2])
    with pytest.raises(ValueError, match="unknown rule"):
        label_drones(predicted, altitudes, "best")
    with pytest.raises(ValueError, match="altitudes"):
        label_drones(predicted, altitudes[:2], "lower")


def test_drone_labels_follow_the_predictions_one_step_later():
    # Drones 1 (40 m) and 2 (20 m), one target; the prediction stored at step t is of t + 1.
    position = np.arange(8, dtype=float).reshape(4, 1, 2)  # labels of steps 0-3
    prediction = np.full((4, 2, 1, 2), np.nan)
    prediction[0, 0] = prediction[0, 1] = 1.0  # both predicted step 1
    prediction[1, 0] = 1.0  # drone 1 alone predicted step 2
    prediction[2, 1] = 1.0  # drone 2 alone predicted step 3
    lower = drone_labels(position, prediction, [40.0, 20.0], "lower")
    assert lower.shape == (2, 4, 1, 2)
    np.testing.assert_array_equal(lower[0, 1], position[1])  # drone 1 with drone 2 below it
    assert np.isnan(lower[0, [0, 2, 3]]).all() and np.isnan(lower[1]).all()
    every = drone_labels(position, prediction, [40.0, 20.0], "all")
    np.testing.assert_array_equal(every, np.broadcast_to(position, (2, 4, 1, 2)))
    with pytest.raises(ValueError, match="prediction"):
        drone_labels(position, prediction[:, :, :0], [40.0, 20.0], "all")


def _pulled(pull, n_steps=400, noise=0.3, seed=0):
    """Three drones and two targets at random spots; each prediction is the target pulled a
    fraction ``pull`` toward its drone, plus ``noise`` m of noise; a few are missing."""
    rng = np.random.default_rng(seed)
    target = rng.uniform(-20, 20, (n_steps, 1, 2, 2))  # (K, 1, N, 2)
    drone = rng.uniform(-20, 20, (n_steps, 3, 2))  # (K, M, 2)
    prediction = (
        target - pull * (target - drone[:, :, None]) + rng.normal(0, noise, (n_steps, 3, 2, 2))
    )
    prediction[rng.random((n_steps, 3, 2)) < 0.2] = np.nan
    return target, drone, prediction


@pytest.mark.parametrize("pull", [0.0, 0.07, 0.2])
def test_the_pull_is_measured_from_the_drones_disagreement(pull):
    _, drone, prediction = _pulled(pull)
    assert estimate_pull(prediction, drone) == pytest.approx(pull, abs=0.005)
    unknown = drone.copy()
    unknown[::3, 1] = np.nan  # steps without telemetry are left out, not NaN
    assert estimate_pull(prediction, unknown) == pytest.approx(pull, abs=0.005)


def test_the_pull_estimate_is_clipped_and_zero_without_a_pair():
    _, drone, pushed = _pulled(-0.2)  # away from the drone
    assert estimate_pull(pushed, drone) == 0.0
    _, drone, prediction = _pulled(0.8)
    assert estimate_pull(prediction, drone) == 0.5
    assert estimate_pull(prediction[:, :1], drone[:, :1]) == 0.0  # one drone: no pair
    with pytest.raises(ValueError, match="drone_position"):
        estimate_pull(prediction, drone[:, :2])


def test_deshrunk_labels_undo_the_pull_toward_each_drone():
    # Drone i's label of step t is the target pulled toward where drone i was at t - 1.
    target, drone, _ = _pulled(0.0)
    where = drone[np.maximum(np.arange(len(drone)) - 1, 0)].transpose(1, 0, 2)[:, :, None]
    labels = target[:, 0][None] - 0.1 * (target[:, 0][None] - where)  # (M, T, N, 2)
    labels[0, :5] = np.nan  # no label: stays none
    fixed = deshrink_labels(labels, drone, 0.1)
    np.testing.assert_allclose(
        fixed[:, 5:], np.broadcast_to(target[5:, 0], (3, len(drone) - 5, 2, 2))
    )
    assert np.isnan(fixed[0, :5]).all()
    np.testing.assert_allclose(deshrink_labels(labels, drone, 0.0)[:, 5:], labels[:, 5:])
    with pytest.raises(ValueError, match="pull"):
        deshrink_labels(labels, drone, 1.0)
