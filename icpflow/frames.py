"""Deprecated, removed in 0.3: the last release's ``icpflow.frames``, today ``icpflow.core.frame_pair``."""

from icpflow.core.deprecation import warn_moved
from icpflow.core.frame_pair import (
    MAX_ARRAY_VALUES,
    MAX_POINT_COLUMNS,
    MAX_POINTS,
    FramePair,
    FramePairError,
    FrameSequence,
    check_points,
    log,
)

__all__ = [
    "FramePair",
    "FramePairError",
    "FrameSequence",
    "MAX_ARRAY_VALUES",
    "MAX_POINTS",
    "MAX_POINT_COLUMNS",
    "check_points",
    "log",
]

warn_moved("icpflow.frames", "icpflow.core.frame_pair")
