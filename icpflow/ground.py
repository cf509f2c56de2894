"""Deprecated, removed in 0.3: the last release's ``icpflow.ground``, today ``icpflow.scans.ground``."""

from icpflow.core.deprecation import warn_moved
from icpflow.scans.ground import (
    DROP_GRADE,
    DROP_M,
    FAR_SLACK,
    FILL_REACH,
    GroundSegmenter,
    below_any_road,
    ground_height,
    object_columns,
)

__all__ = [
    "DROP_GRADE",
    "DROP_M",
    "FAR_SLACK",
    "FILL_REACH",
    "GroundSegmenter",
    "below_any_road",
    "ground_height",
    "object_columns",
]

warn_moved("icpflow.ground", "icpflow.scans.ground")
