"""Deprecated, removed in 0.3: the last release's ``icpflow.baselines``, today ``icpflow.evaluation.baselines``."""

from icpflow.core.deprecation import warn_moved
from icpflow.evaluation.baselines import (
    ego_only_flow,
    zero_flow,
)

__all__ = [
    "ego_only_flow",
    "zero_flow",
]

warn_moved("icpflow.baselines", "icpflow.evaluation.baselines")
