"""Deprecated, removed in 0.3: the last release's ``icpflow.preprocess``, today ``icpflow.scans.preprocess``."""

from icpflow.core.deprecation import warn_moved
from icpflow.scans.preprocess import (
    HeightFrame,
    Preprocessing,
    PreprocessingError,
    estimate_ground_height,
    implausible,
    lift_points,
    lift_pose,
    lift_transform,
)

__all__ = [
    "HeightFrame",
    "Preprocessing",
    "PreprocessingError",
    "estimate_ground_height",
    "implausible",
    "lift_points",
    "lift_pose",
    "lift_transform",
]

warn_moved("icpflow.preprocess", "icpflow.scans.preprocess")
