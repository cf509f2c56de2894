"""Deprecated, removed in 0.3: the last release's ``icpflow.synthetic.lidar``,
today ``icpflow.datasets.synthetic.lidar``."""

from icpflow.core.deprecation import warn_moved
from icpflow.datasets.synthetic.lidar import (
    ELEVATIONS,
    EPS,
    SENSOR_HEIGHT,
    Lidar,
    Scan,
    cast,
    intersect,
    surface_distance,
)

__all__ = [
    "ELEVATIONS",
    "EPS",
    "Lidar",
    "SENSOR_HEIGHT",
    "Scan",
    "cast",
    "intersect",
    "surface_distance",
]

warn_moved("icpflow.synthetic.lidar", "icpflow.datasets.synthetic.lidar")
