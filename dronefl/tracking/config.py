"""The settings of the cloud fusion (:class:`FusionConfig`), apart from the fusion that reads
them (:mod:`dronefl.tracking.fusion`) and its methods (:mod:`dronefl.tracking.methods`)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from dronefl.settings import FUSION_METHODS
from dronefl.tracking.ekf import CHI2_2DOF_99, CHI2_2DOF_999
from dronefl.tracking.models import (
    ConstantVelocity,
    CoordinatedTurn,
    MeanRevertingVelocity,
    MotionModel,
)

#: How two or more drones' noise is shared (:attr:`FusionConfig.noise_split`).
NOISE_SPLITS: tuple[str, ...] = ("adaptive", "reported")
#: The target motion models by name (:attr:`FusionConfig.motion`).
MOTIONS: tuple[str, ...] = ("constant_velocity", "mean_reverting", "coordinated_turn")
#: :attr:`FusionConfig.temporal_kernel` as fitted
#: (:func:`~dronefl.experiments.replay.fit_temporal_kernel`, 5 taps) on two crop-field
#: episodes of Case 2 with the fixed models (``dronefl track --env crop_field --scenario case2
#: --method fixed --seed 20`` and ``21``; 16,000 steps, the truth known there): the drones'
#: sent predictions lag a random-walk target, and the kernel extrapolates (+1.48 on the newest,
#: -0.53 on the one before). 5 taps, not 10: a 10-tap kernel also weighs lag 5, the
#: simulator's 1 s velocity redraw, which real vehicles do not have.
TEMPORAL_KERNEL: tuple[float, ...] = (1.4806, -0.5331, -0.0056, -0.1841, 0.2422)


def _finite_weights(name: str, values: object) -> tuple[float, ...]:
    """``values`` (a tuple, or a list when read back from JSON) as a tuple of floats;
    ``ValueError`` naming ``name`` unless it is a non-empty sequence of finite numbers."""
    numbers = tuple(values)
    if not numbers or not all(isinstance(v, int | float) and math.isfinite(v) for v in numbers):
        raise ValueError(f"{name}: must be finite weights, got {values!r}")
    return tuple(float(v) for v in numbers)


@dataclass(frozen=True)
class FusionConfig:
    """Settings of the cloud fusion (SPEC §6).

    ``method``: the fusion method, a key of :data:`~dronefl.tracking.methods.FUSION_METHODS`
    (``robust`` by default; ``paper`` is the paper's sequential adaptive EKF).
    ``motion``: one of :data:`MOTIONS`: ``constant_velocity`` (x, y, vx, vy),
    ``mean_reverting`` (the same state, the velocity forgetting itself over
    ``velocity_time_constant`` s) or ``coordinated_turn`` (x, y, v, psi, omega).
    ``acceleration_psd``: white-acceleration PSD q, m^2/s^3 (0.5 m/s vehicles turning at the
    headlands need ~0.01-0.1; the random-walk targets of Case 2 change velocity by ~1 m/s each
    second and need ~1). ``turn_rate_psd``: turn-acceleration PSD of the coordinated-turn model,
    rad^2/s^3. ``initial_noise_std``: std of every pair's starting ``R = sigma^2 I``, m.
    ``initial_speed_std``: velocity std of a newborn track, m/s. ``adaptive``: adapt ``R`` per
    pair (off: ``R`` stays at its initial value). ``adaptation_rate``: EMA rate ``beta`` per
    accepted update. ``noise_floor_std``: ``R``'s smallest allowed std, m. ``gate``: squared
    Mahalanobis threshold (chi-square 2 dof 99 % by default), ``None`` disables gating.
    ``reset_after``: re-initialise a track from the measurements when every measurement of it was
    gated out on this many consecutive updates (a lost track cannot recover through the gate),
    ``None`` never.

    ``robust`` only (:class:`~dronefl.tracking.methods.RobustAdaptive`): ``huber_threshold``
    ``k^2``, the squared Mahalanobis distance beyond which a measurement's weight falls as
    ``k / d``; ``consensus_gate``: the squared distance (chi-square 2 dof 99.9 % by default) at
    which a measurement is rejected against the other drones' mean when two or more drones see
    the target (``None``: against the prior, with ``gate``, as the paper); ``fading``: inflate
    the prior of a track that the drones' consensus finds outside ``gate`` (a lagging track);
    ``noise_estimate``: how ``R`` adapts when two or more drones see the target, ``consensus``
    (leave-one-out residuals), ``grubbs`` (the prior as the third corner) or ``innovation`` (the
    paper's form, always used for a lone drone); ``error_autocorrelation`` ``phi``: lag-1
    autocorrelation of the prediction errors, ``R`` inflated by ``(1 + phi) / (1 - phi)`` in
    the update (an AR(1) error's effective-sample-size factor); ``noise_split``: how the
    adapted ``R`` of two or more drones on one target is shared between them, ``adaptive``
    (as it adapts) or ``reported`` (their total kept, shared in proportion to the noise the
    drones report with their predictions, :mod:`dronefl.tracking.reports`; targets whose
    drones did not all report keep ``adaptive``);
    ``temporal_kernel`` ``(w_0, ..., w_{L-1})``, summing to 1: the position the Fuser *outputs*
    for a target (:attr:`Fuser.tracks`, :meth:`Fuser.forecast`) is ``sum_l w_l m_{t-l}``, ``m``
    the ``R``-weighted mean of the fused predictions of the drones that sent the target at
    each of the last ``L`` updates, where there are any (:data:`TEMPORAL_KERNEL`, fitted for
    one update per step of 0.2 s, as the closed loop and the deployed cloud make them); the
    filter's state, history and labels are unchanged; ``None`` (default): the filter's
    position.
    """

    method: str = "robust"
    motion: Literal["constant_velocity", "mean_reverting", "coordinated_turn"] = "constant_velocity"
    acceleration_psd: float = 0.1
    turn_rate_psd: float = 0.01
    velocity_time_constant: float = 1.0
    initial_noise_std: float = 1.0
    initial_speed_std: float = 1.0
    adaptive: bool = True
    adaptation_rate: float = 0.02
    noise_floor_std: float = 0.05
    gate: float | None = CHI2_2DOF_99
    reset_after: int | None = 5
    huber_threshold: float = CHI2_2DOF_99
    error_autocorrelation: float = 0.0
    consensus_gate: float | None = CHI2_2DOF_999
    fading: bool = True
    noise_estimate: str = "consensus"
    noise_split: Literal["adaptive", "reported"] = "adaptive"
    temporal_kernel: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.method not in FUSION_METHODS:  # the names of tracking.methods' registry
            raise ValueError(
                f"method: unknown fusion method {self.method!r} ({', '.join(FUSION_METHODS)})"
            )
        if self.motion not in MOTIONS:
            raise ValueError(f"motion: unknown model {self.motion!r} ({', '.join(MOTIONS)})")
        for name in (
            "acceleration_psd",
            "turn_rate_psd",
            "velocity_time_constant",
            "initial_noise_std",
            "initial_speed_std",
            "noise_floor_std",
            "huber_threshold",
        ):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: must be a positive finite number, got {value!r}")
        if not 0 < self.adaptation_rate <= 1:
            raise ValueError(f"adaptation_rate: must be in (0, 1], got {self.adaptation_rate}")
        if not 0 <= self.error_autocorrelation < 1:
            raise ValueError(
                f"error_autocorrelation: must be in [0, 1), got {self.error_autocorrelation}"
            )
        if self.noise_estimate not in ("consensus", "innovation", "grubbs"):
            raise ValueError(
                f"noise_estimate: {self.noise_estimate!r} is not one of consensus, innovation, "
                "grubbs"
            )
        if self.noise_split not in NOISE_SPLITS:
            raise ValueError(
                f"noise_split: {self.noise_split!r} is not one of {', '.join(NOISE_SPLITS)}"
            )
        if self.noise_split == "reported" and self.method != "robust":
            raise ValueError("noise_split: 'reported' needs the robust fusion method")
        if self.temporal_kernel is not None:
            weights = _finite_weights("temporal_kernel", self.temporal_kernel)
            if abs(sum(weights) - 1.0) > 1e-9:
                raise ValueError(f"temporal_kernel: the weights must sum to 1, got {sum(weights)}")
            object.__setattr__(self, "temporal_kernel", weights)
        for name in ("gate", "consensus_gate"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise ValueError(f"{name}: must be > 0 (squared Mahalanobis distance), got {value}")
        if self.reset_after is not None and self.reset_after < 1:
            raise ValueError(f"reset_after: must be >= 1 update or None, got {self.reset_after}")

    def motion_model(self) -> MotionModel:
        """The configured :class:`MotionModel`."""
        if self.motion == "coordinated_turn":
            return CoordinatedTurn(self.acceleration_psd, self.turn_rate_psd)
        if self.motion == "mean_reverting":
            return MeanRevertingVelocity(self.acceleration_psd, self.velocity_time_constant)
        return ConstantVelocity(self.acceleration_psd)
