"""Deprecated, removed in 0.3: the last release's ``icpflow.normals``, today ``icpflow.scans.normals``."""

from icpflow.core.deprecation import warn_moved
from icpflow.scans.normals import (
    plane_normals,
    smallest_axes,
)

__all__ = [
    "plane_normals",
    "smallest_axes",
]

warn_moved("icpflow.normals", "icpflow.scans.normals")
