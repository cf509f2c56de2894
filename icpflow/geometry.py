"""Deprecated, removed in 0.3: the last release's ``icpflow.geometry``, today ``icpflow.core.geometry``."""

from icpflow.core.deprecation import warn_moved
from icpflow.core.geometry import (
    ROTATION_ATOL,
    ego_flow,
    euler_angles,
    full_to_residual,
    invert,
    is_rigid,
    kabsch,
    lengths,
    make_transform,
    orthonormalized,
    pose_error,
    relative_transform,
    residual_to_full,
    rigid_flow,
    rigid_problem,
    transform_points,
)

__all__ = [
    "ROTATION_ATOL",
    "ego_flow",
    "euler_angles",
    "full_to_residual",
    "invert",
    "is_rigid",
    "kabsch",
    "lengths",
    "make_transform",
    "orthonormalized",
    "pose_error",
    "relative_transform",
    "residual_to_full",
    "rigid_flow",
    "rigid_problem",
    "transform_points",
]

warn_moved("icpflow.geometry", "icpflow.core.geometry")
