"""Deprecated, removed in 0.3: the last release's ``icpflow.synthetic.sequence``,
today ``icpflow.datasets.synthetic.drive``."""

from icpflow.core.deprecation import warn_moved
from icpflow.datasets.synthetic.drive import (
    scan,
    sequence,
)

__all__ = [
    "scan",
    "sequence",
]

warn_moved("icpflow.synthetic.sequence", "icpflow.datasets.synthetic.drive")
