"""Deprecated, removed in 0.3: the last release's ``fastflow3d.options``, today ``fastflow3d.training.options``."""

from fastflow3d.training.options import (
    AugmentOptions,
    DataOptions,
    ExportOptions,
    ExportStepOptions,
    LossOptions,
    MetricsOptions,
    TrainerOptions,
    TrainOptions,
    register,
)
from icpflow.core.deprecation import warn_moved

__all__ = [
    "AugmentOptions",
    "DataOptions",
    "ExportOptions",
    "ExportStepOptions",
    "LossOptions",
    "MetricsOptions",
    "TrainOptions",
    "TrainerOptions",
    "register",
]

warn_moved("fastflow3d.options", "fastflow3d.training.options")
