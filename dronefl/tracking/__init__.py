"""Cloud-side fusion: target motion models, the adaptive EKF and multi-drone fusion (SPEC §6)."""

from dronefl.tracking.adaptive import AdaptiveMeasurementNoise
from dronefl.tracking.ekf import CHI2_2DOF_99, ExtendedKalmanFilter, UpdateDiagnostics
from dronefl.tracking.fusion import (
    Fuser,
    FusionConfig,
    PositionMeasurement,
    Track,
    TrackForecast,
)
from dronefl.tracking.models import ConstantVelocity, CoordinatedTurn, MotionModel

__all__ = [
    "CHI2_2DOF_99",
    "AdaptiveMeasurementNoise",
    "ConstantVelocity",
    "CoordinatedTurn",
    "ExtendedKalmanFilter",
    "FusionConfig",
    "Fuser",
    "MotionModel",
    "PositionMeasurement",
    "Track",
    "TrackForecast",
    "UpdateDiagnostics",
]
