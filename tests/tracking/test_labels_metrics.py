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
from dronefl.tracking.labels import drone_labels, label_drones

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
    # Step 0: drones 1 and 2 see target 1; step 1: drone 1 alone; drone 3 sees target 2 at
    # both steps.
    predicted = np.zeros((2, 3, 2), dtype=bool)
    predicted[0, :2, 0] = True
    predicted[1, 0, 0] = True
    predicted[:, 2, 1] = True
    assert label_drones(predicted, "all").all()
    others = label_drones(predicted, "others")
    assert others[:, :, 0].tolist() == [[True, False], [True, False], [False, False]]
    assert not others[:, :, 1].any()  # drone 3 alone sees target 2
    # Drones that withhold undetected predictions (drone.detected_only): a drone watching the
    # target learns the steps another drone's prediction reached the cloud, its own or not.
    assigned = np.array([[True, False], [True, False], [True, True]])
    watched = label_drones(predicted, "others", assigned)
    assert watched[:, :, 0].tolist() == [[True, False], [True, True], [True, True]]
    assert not watched[:, :, 1].any()
    with pytest.raises(ValueError, match="assigned"):
        label_drones(predicted, "others", assigned[:2])
    with pytest.raises(ValueError, match="unknown rule"):
        label_drones(predicted, "best")


def test_drone_labels_follow_the_predictions_one_step_later():
    # Drones 1 and 2, one target; the prediction stored at step t is of t + 1.
    position = np.arange(8, dtype=float).reshape(4, 1, 2)  # labels of steps 0-3
    prediction = np.full((4, 2, 1, 2), np.nan)
    prediction[0, 0] = prediction[0, 1] = 1.0  # both predicted step 1
    prediction[1, 0] = 1.0  # drone 1 alone predicted step 2
    prediction[2, 1] = 1.0  # drone 2 alone predicted step 3
    others = drone_labels(position, prediction, "others")
    assert others.shape == (2, 4, 1, 2)
    for i in (0, 1):  # each with the other's view of step 1 only
        np.testing.assert_array_equal(others[i, 1], position[1])
        assert np.isnan(others[i, [0, 2, 3]]).all()
    every = drone_labels(position, prediction, "all")
    np.testing.assert_array_equal(every, np.broadcast_to(position, (2, 4, 1, 2)))
    with pytest.raises(ValueError, match="prediction"):
        drone_labels(position, prediction[:, :, :0], "all")
