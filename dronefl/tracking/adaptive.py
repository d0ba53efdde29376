"""Adaptive measurement noise: innovation-based estimation of ``R`` for one (drone, target) pair."""

from __future__ import annotations

import math

import numpy as np

from dronefl.tracking.ekf import UpdateDiagnostics


def floor_eigenvalues(matrix: np.ndarray, floor: float) -> np.ndarray:
    """The symmetric part of ``matrix`` ``(2, 2)`` with every eigenvalue raised to ``floor``
    (the nearest matrix, in Frobenius norm, whose spectrum is ``>= floor``)."""
    sym = 0.5 * (matrix + matrix.T)
    values, vectors = np.linalg.eigh(sym)
    if values[0] >= floor:
        return sym
    return (vectors * np.maximum(values, floor)) @ vectors.T


def truncated_second_moment(gate: float) -> float:
    """``E[w_1^2 | w^T w <= gate]`` for ``w ~ N(0, I_2)``: the factor by which gating at
    ``gate`` shrinks each innovation variance of a consistent 2-D filter."""
    tail = math.exp(-gate / 2.0)
    return (2.0 - (gate + 2.0) * tail) / (2.0 * (1.0 - tail))


class AdaptiveMeasurementNoise:
    r"""Online estimate of the noise covariance ``R`` (m^2) of one drone's predictions of a target.

    Innovation-based adaptive estimation (Mohamed & Schwarz 1999, eq. 23), with the sliding
    window replaced by an exponential moving average of rate ``beta`` (Akhlaghi et al. 2017):

    .. math::
        R_k = \lfloor (1 - \beta) R_{k-1} + \beta\,(y_k y_k^T - H P^-_k H^T) \rfloor_{r_{min}}

    where ``y_k`` is the innovation of the pair's accepted update, ``H P^-_k H^T`` the predicted
    position covariance it was computed against, and ``\lfloor\cdot\rfloor_{r_{min}}`` raises
    every eigenvalue to at least ``r_min`` (m^2) so that ``R`` stays positive definite.

    Why this form and not the residual form ``eps eps^T + H P^+ H^T`` of Akhlaghi et al.: for a
    consistent filter ``E[y y^T] = H P^- H^T + R``, so the innovation form is unbiased and moves
    toward the true ``R`` by a fixed fraction ``beta`` per update whatever the current estimate.
    The residual form is unbiased too, but when ``R`` is underestimated (``R << H P^- H^T``) it
    grows only at second order in ``R`` (the residual shrinks with the gain), so a too-confident
    starting value recovers very slowly; its one advantage, positive definiteness by
    construction, the eigenvalue floor provides here. Single-sample terms ``y y^T - H P^- H^T``
    are often indefinite; the average is not, and the floor only acts when the true noise is
    below ``r_min``.

    Only accepted updates adapt ``R``: a gated-out outlier must not inflate the noise of a
    drone whose other predictions are good. Gating at ``d^2 <= g`` truncates the innovations, so
    for a consistent filter ``E[y y^T | accepted] = c_g S`` with
    ``c_g = (2 - (g + 2) e^{-g/2}) / (2 (1 - e^{-g/2}))`` (0.953 at the 99 % gate); the sample
    is divided by ``c_g`` so that the estimate is not biased low (``gate=None``: ``c_g = 1``).
    """

    def __init__(
        self, initial: np.ndarray, beta: float, floor: float, gate: float | None = None
    ) -> None:
        initial = np.asarray(initial, dtype=float)
        if initial.shape != (2, 2) or not np.isfinite(initial).all():
            raise ValueError(f"initial R must be a finite (2, 2) matrix, got shape {initial.shape}")
        if not 0 < beta <= 1:
            raise ValueError(f"beta must be in (0, 1], got {beta}")
        if not (math.isfinite(floor) and floor > 0):
            raise ValueError(f"floor must be > 0 m^2, got {floor}")
        if gate is not None and not gate > 0:
            raise ValueError(f"gate must be > 0, got {gate}")
        self.beta = float(beta)
        self.truncation = 1.0 if gate is None else truncated_second_moment(gate)
        self.floor = float(floor)
        self.covariance = floor_eigenvalues(initial, self.floor)

    def observe(self, diagnostics: UpdateDiagnostics) -> None:
        """Fold in one update's innovation (ignored when the update was gated out)."""
        if not diagnostics.accepted:
            return
        y = diagnostics.innovation
        sample = np.outer(y, y) / self.truncation - diagnostics.predicted_covariance
        blended = (1.0 - self.beta) * self.covariance + self.beta * sample
        self.covariance = floor_eigenvalues(blended, self.floor)
