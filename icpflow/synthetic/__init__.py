"""Deprecated, removed in 0.3: the last release's ``icpflow.synthetic``, today ``icpflow.datasets.synthetic``; its
modules (``icpflow.synthetic.lidar``, ...) are shims of their own."""

from icpflow.core.deprecation import warn_moved
from icpflow.datasets.synthetic import (
    AV2_META_CLASSES,
    CLASSES,
    ELEVATIONS,
    Lidar,
    Scan,
    Scene,
    build_scene,
    cast,
    scan,
    sequence,
)

__all__ = [
    "AV2_META_CLASSES",
    "CLASSES",
    "ELEVATIONS",
    "Lidar",
    "Scan",
    "Scene",
    "build_scene",
    "cast",
    "scan",
    "sequence",
]

warn_moved("icpflow.synthetic", "icpflow.datasets.synthetic")
