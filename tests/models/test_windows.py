"""Windows: which exist, their labels, masking of missed detections, the chronological split."""

import numpy as np
import pytest

from dronefl.models.windows import (
    FEATURE_DIM,
    PositionFrame,
    WindowSpec,
    build_windows,
    split_windows,
    window_features,
)


def test_windows_of_assigned_target_with_relative_labels(tiny_log):
    log, labels = tiny_log
    spec = WindowSpec(past_steps=3, future_steps=2)

    windows = build_windows(log, labels, spec)

    # Window times t = 2 .. 13; those whose 3 past steps all lie in the miss (t = 6, 7, 8) go.
    assert windows.t_index.tolist() == [2, 3, 4, 5, 9, 10, 11, 12, 13]
    assert set(windows.target_ids.tolist()) == {1}
    assert windows.features.shape == (9, 3, FEATURE_DIM)
    # Labels: target at (t+1, 0) and (t+2, 0) m, minus the drone at (10, 20) m.
    t = 9
    k = windows.t_index.tolist().index(t)
    np.testing.assert_allclose(windows.labels[k], [[t + 1 - 10, -20], [t + 2 - 10, -20]])
    np.testing.assert_allclose(windows.origin[k], [10, 20])
    np.testing.assert_allclose(windows.altitude, 30.0)


def test_missed_steps_carry_no_box_and_a_zero_flag(tiny_log):
    log, labels = tiny_log
    windows = build_windows(log, labels, WindowSpec(past_steps=3, future_steps=2))
    k = windows.t_index.tolist().index(5)  # steps 3 (seen), 4, 5 (missed)
    features = windows.features[k]
    expected = [2 * (0.4 - 0.5), 2 * (0.6 - 0.5), 0.5, 0.3]
    np.testing.assert_allclose(features[0, :4], expected, rtol=1e-6)
    np.testing.assert_array_equal(features[1:, :4], 0.0)
    np.testing.assert_array_equal(features[:, -1], [1.0, 0.0, 0.0])


def test_box_values_at_missed_steps_do_not_reach_the_features():
    rng = np.random.default_rng(0)
    detected = np.array([True, False, True])
    odometry = rng.normal(size=(3, 12))
    boxes_nan = rng.uniform(size=(3, 4))
    boxes_nan[1] = np.nan
    boxes_junk = boxes_nan.copy()
    boxes_junk[1] = (9.0, -9.0, 5.0, 7.0)
    origin = np.zeros(2)
    a = window_features(boxes_nan, detected, odometry, origin, PositionFrame())
    b = window_features(boxes_junk, detected, odometry, origin, PositionFrame())
    np.testing.assert_array_equal(a, b)
    assert np.isfinite(a).all()


def test_pseudo_labels_with_gaps_drop_their_windows(tiny_log):
    log, labels = tiny_log
    tracks = labels.copy()
    tracks[12, 0] = np.nan  # no fused track at step 12
    windows = build_windows(log, tracks, WindowSpec(past_steps=3, future_steps=2))
    # Windows t = 10 and 11 need step 12 as a future label.
    assert 10 not in windows.t_index and 11 not in windows.t_index
    assert 9 in windows.t_index and 12 in windows.t_index


def test_chronological_split_never_shares_a_step(tiny_log):
    log, labels = tiny_log
    spec = WindowSpec(past_steps=2, future_steps=1, train_fraction=0.5)
    train, test = split_windows(log, labels, spec)
    # Split at step 8: training windows end (t + L_f) before it, test windows start after it.
    assert (train.t_index + 1).max() < 8
    assert (test.t_index - 1).min() >= 8


def test_training_on_everything_leaves_no_test_windows(tiny_log):
    log, labels = tiny_log
    spec = WindowSpec(past_steps=2, future_steps=1, train_fraction=1.0)
    train, test = split_windows(log, labels, spec)
    assert len(test) == 0
    assert len(train) == len(build_windows(log, labels, spec))
    with pytest.raises(ValueError, match=r"train_fraction must be in \(0, 1\]"):
        WindowSpec(train_fraction=1.5)


def test_labels_of_the_wrong_shape_are_rejected(tiny_log):
    log, labels = tiny_log
    with pytest.raises(ValueError, match="labels must have shape"):
        build_windows(log, labels[:, :1], WindowSpec())


def test_absolute_positions_follow_the_scenario_field(tiny_log):
    # A 200 m x 100 m field: origin at its centre (100, 50) m, 100 m (half the width) per unit.
    log, labels = tiny_log
    frame = PositionFrame(relative=False, field_m=(200.0, 100.0))
    assert frame.field_centre_m == (100.0, 50.0) and frame.scale_m == 100.0
    spec = WindowSpec(past_steps=3, future_steps=2, relative=False, field_m=(200.0, 100.0))
    windows = build_windows(log, labels, spec)
    np.testing.assert_allclose(windows.origin, np.broadcast_to([100.0, 50.0], (len(windows), 2)))
    # The drone hovers at (10, 20) m: x feature (10 - 100) / 100, y feature (20 - 50) / 100.
    np.testing.assert_allclose(windows.features[0, 0, 4:6], [-0.9, -0.3], rtol=1e-6)
    assert PositionFrame().scale_m == 10.0  # relative: 10 m per unit, whatever the field
