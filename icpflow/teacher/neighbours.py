"""Deprecated, removed in 0.3: the last release's ``icpflow.teacher.neighbours``, today ``icpflow.scans.neighbours``."""

from icpflow.core.deprecation import warn_moved
from icpflow.scans.neighbours import (
    GAVE_UP,
    MAX_KNN_SHELL,
    build_grid,
    k_nearest,
    nearest,
    nearest_distances,
    nn_stats,
    transform_cloud,
)

__all__ = [
    "GAVE_UP",
    "MAX_KNN_SHELL",
    "build_grid",
    "k_nearest",
    "nearest",
    "nearest_distances",
    "nn_stats",
    "transform_cloud",
]

warn_moved("icpflow.teacher.neighbours", "icpflow.scans.neighbours")
