"""Pose losses: the SE(3) geodesic loss, the baselines, and the metric weights Z."""

from svr.losses.baselines import (
    PoseNetLoss,
    anchor_point_loss,
    posenet_loss,
    rotation_6d_loss,
)
from svr.losses.metric_weights import (
    DEFAULT_LENGTH_SCALE_MM,
    default_metric_weights,
    estimate_metric_weights,
    validate_metric_weights,
)
from svr.losses.se3 import SE3GeodesicLoss, se3_geodesic_loss

__all__ = [
    "DEFAULT_LENGTH_SCALE_MM",
    "PoseNetLoss",
    "SE3GeodesicLoss",
    "anchor_point_loss",
    "default_metric_weights",
    "estimate_metric_weights",
    "posenet_loss",
    "rotation_6d_loss",
    "se3_geodesic_loss",
    "validate_metric_weights",
]
