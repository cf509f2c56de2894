"""The embedded synthetic LiDAR world: a seeded street scene, a spinning ray-caster and exact ground truth."""

from icpflow.synthetic.lidar import ELEVATIONS, Lidar, Scan, cast
from icpflow.synthetic.scene import AV2_META_CLASSES, CLASSES, Scene, build_scene
from icpflow.synthetic.sequence import scan, sequence

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
