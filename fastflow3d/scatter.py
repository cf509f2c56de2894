"""Deprecated, removed in 0.3: the last release's ``fastflow3d.scatter``, today ``fastflow3d.network.scatter``."""

from fastflow3d.network.scatter import scatter_mean, scatter_sum, to_pseudo_image
from icpflow.core.deprecation import warn_moved

__all__ = ["scatter_mean", "scatter_sum", "to_pseudo_image"]

warn_moved("fastflow3d.scatter", "fastflow3d.network.scatter")
