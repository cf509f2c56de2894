"""A synthetic scene ray-cast into a :class:`~icpflow.core.frame_pair.FrameSequence` with exact ground truth.

Scan t of a sequence is ``cast(scene, t, lidar, rng)`` with its own noise generator seeded by (seed, t), so a scan
is the same whichever frames are generated and in which order. Ground truth comes from the scene: per point the
hit primitive gives the class and instance, and ``object_poses`` (world_from_object per frame, every agent) let
:meth:`FrameSequence.pair` compute the exact full flow; ground = points that hit the ground height field.
"""

from __future__ import annotations

import numpy as np

from icpflow.core.frame_pair import FrameSequence
from icpflow.datasets.synthetic.lidar import Lidar, Scan, cast
from icpflow.datasets.synthetic.scene import Scene


def scan(scene: Scene, frame: int, lidar: Lidar, noise: bool = True) -> Scan:
    """Scan ``frame`` of ``scene``; ``noise=False`` gives the noise-free scan without dropout."""
    rng = np.random.default_rng([scene.seed, frame]) if noise else None
    return cast(scene, frame, lidar, rng)


def sequence(scene: Scene, lidar: Lidar, frames=None, noise: bool = True, log_id: str = "") -> FrameSequence:
    """The scans ``frames`` (default all, ascending) of ``scene`` as a FrameSequence with exact ground truth."""
    frames = list(range(scene.frames)) if frames is None else list(frames)
    scans = [scan(scene, t, lidar, noise) for t in frames]
    labels = [scene.labels(s.primitive) for s in scans]
    objects = {key: value[frames] for key, value in scene.object_poses().items()}
    return FrameSequence(
        points=[s.points for s in scans],
        poses=scene.ego_poses[frames],
        timestamps_ns=scene.timestamps_ns[frames],
        ground=[s.primitive == 0 for s in scans],
        classes=[c for c, _ in labels],
        instance=[i for _, i in labels],
        object_poses=objects,
        log_id=log_id or f"synthetic-{scene.seed}",
        source=f"synthetic seed {scene.seed}",
    )
