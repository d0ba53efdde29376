"""Cloud-side fusion: target motion models, the adaptive EKF, multi-drone fusion, RTS smoothing,
pseudo-labels and track metrics (SPEC §6, §8)."""

from dronefl.tracking.adaptive import AdaptiveMeasurementNoise
from dronefl.tracking.ekf import CHI2_2DOF_99, ExtendedKalmanFilter, UpdateDiagnostics
from dronefl.tracking.fusion import (
    RANDOM_WALK_VELOCITY_TIME_CONSTANT,
    CloudFusion,
    Fuser,
    FusionConfig,
    PositionMeasurement,
    Track,
    TrackForecast,
    cloud_fusion,
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
    "FUSION_METHODS",
    "LABEL_SOURCES",
    "RANDOM_WALK_VELOCITY_TIME_CONSTANT",
    "AdaptiveMeasurementNoise",
    "CloudFusion",
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
    "cloud_fusion",
    "make_labels",
    "rts_smooth",
    "set_distances",
]
