"""Fixed-interval Rauch-Tung-Striebel smoothing of a fused track's recorded forward pass.

The :class:`~dronefl.tracking.fusion.Fuser` records, for every update of every target, the prior
it predicted, the transition Jacobian it used and the posterior it reached
(:class:`TrackHistory`); :func:`rts_smooth` runs the backward pass over that record. A track that
was born or reset starts a new segment: segments are smoothed independently, since no transition
links a reset track to the one before it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TrackHistory:
    """The forward pass of one target's filter, one row per update (``S`` rows).

    ``t`` ``(S,)`` s: update times. ``prior_mean`` ``(S, n)`` / ``prior_covariance``
    ``(S, n, n)``: ``x^-_s``, ``P^-_s`` predicted from row ``s - 1`` (at a segment start: the
    newborn state, equal to the posterior). ``transition`` ``(S, n, n)``: the Jacobian ``F_s`` of
    that prediction (identity at a segment start). ``mean`` ``(S, n)`` / ``covariance``
    ``(S, n, n)``: the posterior ``x^+_s``, ``P^+_s``. ``start`` ``(S,)``: a segment (birth or
    reset) begins at row ``s``. ``accepted`` ``(S,)``: measurements fused at row ``s``. State
    units are the motion model's (position first, m).
    """

    target_id: int
    t: np.ndarray
    prior_mean: np.ndarray
    prior_covariance: np.ndarray
    transition: np.ndarray
    mean: np.ndarray
    covariance: np.ndarray
    start: np.ndarray
    accepted: np.ndarray

    def __len__(self) -> int:
        return len(self.t)


@dataclass(frozen=True)
class SmoothedTrack:
    """Smoothed estimates ``x^s_s`` ``(S, n)`` and ``P^s_s`` ``(S, n, n)`` of one target on its
    history's update times ``t`` ``(S,)`` s."""

    target_id: int
    t: np.ndarray
    mean: np.ndarray
    covariance: np.ndarray

    @property
    def position(self) -> np.ndarray:
        """Smoothed positions ``(S, 2)``, m."""
        return self.mean[:, :2]

    @property
    def position_covariance(self) -> np.ndarray:
        """Smoothed position covariances ``(S, 2, 2)``, m^2."""
        return self.covariance[:, :2, :2]


def rts_smooth(history: TrackHistory) -> SmoothedTrack:
    r"""Rauch-Tung-Striebel backward pass over ``history`` (Särkkä 2013, Thm. 8.2; the extended
    form for a nonlinear model, Thm. 9.1, with the Jacobians the forward pass used):

    .. math::
        C_s = P^+_s F_{s+1}^T (P^-_{s+1})^{-1},\quad
        x^s_s = x^+_s + C_s (x^s_{s+1} - x^-_{s+1}),\quad
        P^s_s = P^+_s + C_s (P^s_{s+1} - P^-_{s+1}) C_s^T

    started from ``x^s = x^+``, ``P^s = P^+`` at the last row of every segment. The gain uses a
    linear solve with ``P^-`` (symmetric positive definite), not an explicit inverse.
    """
    mean = history.mean.copy()
    cov = history.covariance.copy()
    for s in range(len(history) - 2, -1, -1):
        if history.start[s + 1]:
            continue  # row s ends a segment: its smoothed state is its filtered one
        f = history.transition[s + 1]
        prior_cov = history.prior_covariance[s + 1]
        # C = P F^T (P^-)^-1  <=>  P^- C^T = F P (P^- and P symmetric)
        gain = np.linalg.solve(prior_cov, f @ history.covariance[s]).T
        mean[s] = history.mean[s] + gain @ (mean[s + 1] - history.prior_mean[s + 1])
        cov[s] = history.covariance[s] + gain @ (cov[s + 1] - prior_cov) @ gain.T
    return SmoothedTrack(history.target_id, history.t.copy(), mean, cov)
