"""The embedded synthetic dataset: a seeded street scene (``scene``), a spinning ray-caster (``lidar``), a drive of
scans with exact ground truth (``drive``), and the reader that serves its splits as frame pairs (``reader``,
``dataset=synthetic``)."""

from icpflow.datasets.synthetic.drive import scan, sequence
from icpflow.datasets.synthetic.lidar import ELEVATIONS, Lidar, Scan, cast
from icpflow.datasets.synthetic.reader import SPLIT_OFFSETS, SPLIT_STRIDE, SyntheticDataset
from icpflow.datasets.synthetic.scene import AV2_META_CLASSES, CLASSES, Scene, build_scene

__all__ = [
    "AV2_META_CLASSES",
    "CLASSES",
    "ELEVATIONS",
    "Lidar",
    "SPLIT_OFFSETS",
    "SPLIT_STRIDE",
    "Scan",
    "Scene",
    "SyntheticDataset",
    "build_scene",
    "cast",
    "scan",
    "sequence",
]
