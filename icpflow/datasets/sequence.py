"""Deprecated, removed in 0.3: the last release's ``icpflow.datasets.sequence``,
today ``icpflow.datasets.scan_folder``."""

from icpflow.core.deprecation import warn_moved
from icpflow.datasets.scan_folder import (
    ScanSequenceDataset,
)

__all__ = [
    "ScanSequenceDataset",
]

warn_moved("icpflow.datasets.sequence", "icpflow.datasets.scan_folder")
