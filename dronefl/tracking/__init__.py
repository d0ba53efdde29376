"""Cloud-side fusion: target motion models, the adaptive EKF, multi-drone fusion, RTS smoothing,
pseudo-labels and track metrics (SPEC §6, §8)."""

from dronefl.tracking.adaptive import AdaptiveMeasurementNoise
from dronefl.tracking.ekf import CHI2_2DOF_99, ExtendedKalmanFilter, UpdateDiagnostics
from dronefl.tracking.fusion import (
    CONSTANT_SPEED_PSD,
    RANDOM_WALK_VELOCITY_TIME_CONSTANT,
    TUNED_CONSTANT_SPEED_PSD,
    Fuser,
    FusionConfig,
    PositionMeasurement,
    Track,
    TrackForecast,
    fusion_config,
)
from dronefl.tracking.labels import LABEL_SOURCES, Labels, LabelSource, make_labels
from dronefl.tracking.methods import FUSION_METHODS, FusionMethod
from dronefl.tracking.models import (
    ConstantVelocity,
    CoordinatedTurn,
    MeanRevertingVelocity,
    MotionModel,
)
from dronefl.tracking.set_distances import SetDistances, set_distances
from dronefl.tracking.smoother import SmoothedTrack, TrackHistory, rts_smooth

__all__ = [
    "CHI2_2DOF_99",
    "CONSTANT_SPEED_PSD",
    "FUSION_METHODS",
    "LABEL_SOURCES",
    "RANDOM_WALK_VELOCITY_TIME_CONSTANT",
    "TUNED_CONSTANT_SPEED_PSD",
    "AdaptiveMeasurementNoise",
    "ConstantVelocity",
    "MeanRevertingVelocity",
    "CoordinatedTurn",
    "ExtendedKalmanFilter",
    "FusionConfig",
    "FusionMethod",
    "Fuser",
    "LabelSource",
    "Labels",
    "MotionModel",
    "PositionMeasurement",
    "SmoothedTrack",
    "Track",
    "TrackForecast",
    "TrackHistory",
    "SetDistances",
    "UpdateDiagnostics",
    "fusion_config",
    "make_labels",
    "rts_smooth",
    "set_distances",
]
