"""Deprecated, removed in 0.3: the last release's ``fastflow3d.refine``, today ``fastflow3d.inference.refine``."""

from fastflow3d.inference.refine import RefineConfig, components, refine_residual
from icpflow.core.deprecation import warn_moved

__all__ = ["RefineConfig", "components", "refine_residual"]

warn_moved("fastflow3d.refine", "fastflow3d.inference.refine")
