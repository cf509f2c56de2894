"""Deprecated, removed in 0.3: the last release's ``icpflow.viz_rerun``, today ``icpflow.viz.recording``."""

from icpflow.core.deprecation import warn_moved
from icpflow.viz.recording import (
    SPEED_COLOURMAP,
    VIEWERS,
    PairRecording,
    ViewerUnavailable,
    check_viewer,
    import_rerun,
    record_pair,
    speed_colours,
)

__all__ = [
    "PairRecording",
    "SPEED_COLOURMAP",
    "VIEWERS",
    "ViewerUnavailable",
    "check_viewer",
    "import_rerun",
    "record_pair",
    "speed_colours",
]

warn_moved("icpflow.viz_rerun", "icpflow.viz.recording")
