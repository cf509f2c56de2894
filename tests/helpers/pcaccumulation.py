"""Files in PCAccumulation's layout (Waymo, nuScenes) written from the synthetic world.

The layout and label encoding are those of PCAccumulation's writers (``dataset_toolbox/prep_nuscene_waymo_sf``):
int64 labels, float32 transforms, anchor = frame 0 = the latest scan, Waymo ``sem_labels`` per point (box type - 1:
0 vehicle, 1 pedestrian, 2 background or sign, 3 cyclist), nuScenes ``sem_labels`` the 16 lidarseg classes of the
anchor frame's points only.
"""

from functools import lru_cache

import numpy as np

from icpflow.core.frame_pair import FrameSequence
from icpflow.core.geometry import invert
from icpflow.datasets.pcaccumulation import PCAccumulationDataset
from icpflow.datasets.synthetic.reader import SyntheticDataset

#: frames per sample and their rate, per dataset
FORMATS = {"waymo": (5, 10.0), "nuscenes": (11, 20.0)}
#: synthetic classes (background, car, other vehicle, pedestrian, cyclist) -> Waymo sem_labels
WAYMO_SEM = np.array([2, 0, 0, 1, 3])
#: the same -> nuScenes lidarseg classes (manmade, car, truck, pedestrian, bicycle); ground is 11 (driveable)
NUSCENES_SEM = np.array([15, 4, 10, 7, 2])
#: -> the classes the reader gives Waymo points (1 vehicle, 2 pedestrian, 3 cyclist)
WAYMO_CLASSES = np.array([0, 1, 1, 2, 3])
SPEED_THRESHOLD = 0.5  # m/s, a box is dynamic when its fastest motion exceeds it


@lru_cache
def world(dataset: str) -> FrameSequence:
    """A small synthetic sequence (32 beams, 2 degree columns) with the dataset's frame count and rate."""
    frames, frequency = FORMATS[dataset]
    return SyntheticDataset(
        "val", num_sequences=1, frames_per_sequence=frames, beams=32, azimuth_resolution_deg=2.0, frequency_hz=frequency
    ).sequence(0)


def pcaccumulation_arrays(sequence: FrameSequence, dataset: str) -> dict[str, np.ndarray]:
    """One PCAccumulation sample of ``sequence`` (scans oldest first): the anchor is the last scan, frame c is scan
    F - 1 - c, rows stacked anchor first; instances numbered 1..K as indices into ``bbox_tsfm`` (0 = none)."""
    frames = len(sequence)
    anchor = frames - 1
    scans = [anchor - c for c in range(frames)]
    world_from_anchor = sequence.poses[anchor]
    anchor_from_world = invert(world_from_anchor)
    ids = sorted(sequence.object_poses)
    number = np.zeros(max(ids) + 1, np.int64)
    number[ids] = np.arange(1, len(ids) + 1)
    boxes = np.tile(np.eye(4), (len(ids) + 1, frames, 1, 1))
    moving = np.zeros(len(ids) + 1, bool)
    seconds = np.diff(sequence.timestamps_ns) * 1e-9
    for key, poses in sequence.object_poses.items():
        for c, t in enumerate(scans):
            boxes[number[key], c] = anchor_from_world @ poses[anchor] @ invert(poses[t]) @ world_from_anchor
        speeds = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1) / seconds
        moving[number[key]] = speeds.max() > SPEED_THRESHOLD
    classes = np.concatenate([sequence.classes[t] for t in scans])
    inst = np.concatenate([number[sequence.instance[t]] for t in scans])
    if dataset == "waymo":
        sem = WAYMO_SEM[classes]
    else:
        sem = np.where(sequence.ground[anchor], 11, NUSCENES_SEM[sequence.classes[anchor]])
    return {
        "raw_points": np.concatenate([sequence.points[t] for t in scans]),
        "time_indice": np.concatenate([np.full(len(sequence.points[t]), c) for c, t in enumerate(scans)]),
        "sd_labels": moving[inst].astype(np.int64),
        "fb_labels": (classes > 0).astype(np.int64),
        "inst_labels": inst,
        "sem_labels": sem.astype(np.int64),
        "ego_motion_gt": np.stack([anchor_from_world @ sequence.poses[t] for t in scans]).astype(np.float32),
        "bbox_tsfm": boxes.astype(np.float32),
    }


@lru_cache
def _cached_arrays(dataset: str) -> dict[str, np.ndarray]:
    return pcaccumulation_arrays(world(dataset), dataset)


def sample_arrays(dataset: str = "waymo") -> dict[str, np.ndarray]:
    """A fresh copy of the dataset's sample arrays (safe to modify)."""
    return {key: value.copy() for key, value in _cached_arrays(dataset).items()}


def write_dataset(root, dataset="waymo", **changes):
    """``<root>/val/seg/000.npz`` holding the sample with ``changes`` (None removes a key)."""
    (root / "val" / "seg").mkdir(parents=True, exist_ok=True)
    arrays = {key: value for key, value in {**sample_arrays(dataset), **changes}.items() if value is not None}
    np.savez(root / "val" / "seg" / "000.npz", **arrays)
    return root / "val" / "seg" / "000.npz"


def reader(root, dataset="waymo", **options) -> PCAccumulationDataset:
    frames, frequency = FORMATS[dataset]
    return PCAccumulationDataset(
        root, "val", frames=frames, frequency_hz=frequency, name=dataset, sem_labels=dataset, **options
    )
