"""Deprecated, removed in 0.3: the last release's ``fastflow3d.augment``, today ``fastflow3d.training.augment``."""

from fastflow3d.training.augment import FLOW_KEYS, PER_POINT, POINT_KEYS, Augmentation, subsample, transform_sample
from icpflow.core.deprecation import warn_moved

__all__ = ["FLOW_KEYS", "PER_POINT", "POINT_KEYS", "Augmentation", "subsample", "transform_sample"]

warn_moved("fastflow3d.augment", "fastflow3d.training.augment")
