"""Deprecated, removed in 0.3: the last release's ``icpflow.teacher.icp``,
today ``icpflow.teacher.registration.icp``."""

from icpflow.core.deprecation import warn_moved
from icpflow.teacher.registration.icp import (
    PLANE_MAX_ITER,
    PLANE_NEIGHBOURS,
    icp_point_to_plane,
    icp_point_to_point,
    normals,
)

__all__ = [
    "PLANE_MAX_ITER",
    "PLANE_NEIGHBOURS",
    "icp_point_to_plane",
    "icp_point_to_point",
    "normals",
]

warn_moved("icpflow.teacher.icp", "icpflow.teacher.registration.icp")
