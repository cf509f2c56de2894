"""Deprecated, removed in 0.3: the last release's ``icpflow.odometry``, today ``icpflow.scans.odometry``."""

from icpflow.core.deprecation import warn_moved
from icpflow.scans.odometry import (
    MIN_EGO_POINTS,
    MIN_SPREAD,
    Odometry,
    OdometryStep,
    TargetPlanes,
    ego_settings,
    estimate_ego_motion,
    kiss_odometry,
    normal_spread,
    voxel_cloud,
)

__all__ = [
    "MIN_EGO_POINTS",
    "MIN_SPREAD",
    "Odometry",
    "OdometryStep",
    "TargetPlanes",
    "ego_settings",
    "estimate_ego_motion",
    "kiss_odometry",
    "normal_spread",
    "voxel_cloud",
]

warn_moved("icpflow.odometry", "icpflow.scans.odometry")
