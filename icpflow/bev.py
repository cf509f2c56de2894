"""Deprecated, removed in 0.3: the last release's ``icpflow.bev``, today ``icpflow.scans.bev``."""

from icpflow.core.deprecation import warn_moved
from icpflow.scans.bev import (
    in_box_cells,
    occupied_cells,
)

__all__ = [
    "in_box_cells",
    "occupied_cells",
]

warn_moved("icpflow.bev", "icpflow.scans.bev")
