"""Deprecated, removed in 0.3: the last release's ``icpflow.synthetic.scene``,
today ``icpflow.datasets.synthetic.scene``."""

from icpflow.core.deprecation import warn_moved
from icpflow.datasets.synthetic.scene import (
    AV2_META_CLASSES,
    CLASSES,
    CROSS_HALF,
    LANES,
    PARKING,
    RANGE_EDGE,
    ROAD_HALF,
    SIDEWALK,
    Ground,
    Scene,
    agent_shapes,
    build_scene,
    unicycle,
)

__all__ = [
    "AV2_META_CLASSES",
    "CLASSES",
    "CROSS_HALF",
    "Ground",
    "LANES",
    "PARKING",
    "RANGE_EDGE",
    "ROAD_HALF",
    "SIDEWALK",
    "Scene",
    "agent_shapes",
    "build_scene",
    "unicycle",
]

warn_moved("icpflow.synthetic.scene", "icpflow.datasets.synthetic.scene")
