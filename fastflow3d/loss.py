"""Deprecated, removed in 0.3: the last release's ``fastflow3d.loss``, today ``fastflow3d.training.loss``."""

from fastflow3d.training.loss import (
    WEIGHTINGS,
    flow_loss,
    grouped_mean_sum,
    object_loss,
    speed_buckets,
    speed_weight,
)
from icpflow.core.deprecation import warn_moved

__all__ = ["WEIGHTINGS", "flow_loss", "grouped_mean_sum", "object_loss", "speed_buckets", "speed_weight"]

warn_moved("fastflow3d.loss", "fastflow3d.training.loss")
