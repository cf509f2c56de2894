"""Waymo and nuScenes as preprocessed by PCAccumulation (Huang et al., ECCV 2022): the ICP-Flow paper's data.

One ``.npz`` per sample holds F consecutive frames (Waymo 5 at 10 Hz, nuScenes 11 at 20 Hz), as PCAccumulation's
``dataset_toolbox/prep_nuscene_waymo_sf`` writes them (integers int64, transforms float32):

* ``raw_points`` (m, 3): all frames stacked, each frame's points in its own sensor frame (before compensation;
  Waymo: the vehicle frame, top LiDAR only; nuScenes: the LiDAR frame);
* ``time_indice`` (m,): 0 is the anchor (the latest frame), c is c frames in the past;
* ``fb_labels`` (m,): 1 = foreground (Waymo: vehicle, pedestrian, cyclist boxes; nuScenes: vehicle, human and
  animal boxes), 0 = background (Waymo's signs too);
* ``sd_labels`` (m,): 1 = dynamic (the point's box moves faster than a speed threshold), else 0;
* ``inst_labels`` (m,): index into ``bbox_tsfm``, 0 = no box (Waymo numbers sign boxes too: static, identity);
* ``sem_labels``: Waymo (m,) the box type - 1, i.e. 0 vehicle, 1 pedestrian, 2 background or sign, 3 cyclist;
  nuScenes: the 16-class lidarseg labels of the anchor frame's points only (not (m,));
* ``ego_motion_gt`` (F, 4, 4): frame c into the anchor frame (identity for the anchor);
* ``bbox_tsfm`` (K, F, 4, 4): instance k's rigid motion from frame c to the anchor, in the anchor frame, so the
  ground-truth position in the anchor of a point p of frame c is ``bbox_tsfm[inst, c] @ ego_motion_gt[c] @ p``
  (identity for static boxes and for frames where a box is not annotated).

Samples are listed by a split file ``<root>/<split>_info.txt`` (one path per line, relative to ``root``; the
reference's ``assets/configs/datasets/<name>/<split>_info.txt``), or else found as ``<root>/<split>/**/*.npz``.

``pair(index, horizon=k)`` is frame c = k (pc0, its own sensor frame) -> the anchor (pc1, its sensor frame),
built by :class:`icpflow.core.frame_pair.FrameSequence` with the anchor frame as world: ``pose0 = ego_motion_gt[k]``,
``pose1 = identity``, object poses ``inv(bbox_tsfm[inst, c])`` per frame, which gives exactly the FULL flow above
minus p. Labels of pc0, in the project's rule (0 = background):

* ``classes`` int32: 0 where ``fb_labels`` is 0; on foreground points, Waymo (``sem_labels="waymo"``):
  ``WAYMO_CLASSES`` (1 vehicle, 2 pedestrian, 3 cyclist; a foreground point with another ``sem_labels`` is an
  error); nuScenes (``sem_labels="nuscenes"``, whose semantic labels cover only the anchor = pc1): 1, foreground
  of unknown class;
* ``instance`` = ``inst_labels`` as stored; ``dynamic`` = ``sd_labels``; no ground labels.

``max_horizon`` is F - 1. A non-rigid ``bbox_tsfm`` entry is an error where its instance has points in that
frame, ignored elsewhere.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from icpflow.core.files import read_text
from icpflow.core.frame_pair import FramePair, FrameSequence, check_points
from icpflow.core.geometry import invert, rigid_problem
from icpflow.datasets.base import PairDataset
from icpflow.datasets.file_formats import fail, load_npz

KEYS = (
    "raw_points", "time_indice", "sd_labels", "fb_labels", "inst_labels", "sem_labels", "ego_motion_gt", "bbox_tsfm",
)  # fmt: skip
PER_POINT = ("time_indice", "sd_labels", "fb_labels", "inst_labels")
#: Waymo ``sem_labels`` of foreground points -> project ``classes`` 1 vehicle, 2 pedestrian, 3 cyclist (2 = background)
WAYMO_CLASSES = {0: 1, 1: 2, 3: 3}
SEM_LABELS = ("waymo", "nuscenes")


class PCAccumulationDataset(PairDataset):
    """PCAccumulation samples (Waymo, nuScenes) as frame pairs into the anchor frame (see the module docstring)."""

    def __init__(
        self,
        root: str | Path,
        split: str = "val",
        frames: int = 5,
        frequency_hz: float = 10.0,
        name: str = "waymo",
        split_file: str | Path | None = None,
        sem_labels: str = "waymo",
    ) -> None:
        if sem_labels not in SEM_LABELS:
            raise ValueError(f"{name}: sem_labels must be one of {', '.join(SEM_LABELS)}, got {sem_labels!r}")
        self.root = Path(root)
        self.sem_labels = sem_labels
        self.split = split
        self.frames = int(frames)
        self.frequency_hz = float(frequency_hz)
        self.name = name
        self.max_horizon = self.frames - 1
        listing = Path(split_file) if split_file is not None else self.root / f"{split}_info.txt"
        if listing.is_file():
            lines = [line.strip() for line in read_text(listing).splitlines() if line.strip()]
            self.files = [self.root / line.lstrip("/") for line in lines]
        elif split_file is not None:
            raise fail(listing, "split file not found")
        else:
            self.files = sorted((self.root / split).rglob("*.npz"))
        if not self.files:
            raise fail(self.root, f"no samples: neither {listing.name} nor .npz files under {split}/")

    def __len__(self) -> int:
        return len(self.files)

    def sample_id(self, index: int) -> str:
        return self.files[index].relative_to(self.root).with_suffix("").as_posix()

    def metadata(self) -> dict:
        return {**super().metadata(), "root": str(self.root), "split": self.split, "frames": self.frames,
                "frequency_hz": self.frequency_hz, "sem_labels": self.sem_labels}  # fmt: skip

    def pair(self, index: int, horizon: int = 1) -> FramePair:
        if not 1 <= horizon <= self.max_horizon:
            raise IndexError(f"{self.name}: horizon {horizon} outside 1..{self.max_horizon}")
        sequence, dynamic = self.sequence(index)
        t0 = self.frames - 1 - horizon
        pair = sequence.pair(t0, horizon)
        return pair.replace(dynamic=dynamic[t0], sample_id=self.sample_id(index) + f"/{horizon}")

    def sequence(self, index: int) -> tuple[FrameSequence, list[np.ndarray]]:
        """The sample as a :class:`FrameSequence` (scans oldest first, anchor last) and per-scan dynamic masks."""
        path = self.files[index]
        data = load_npz(path, KEYS, optional=())
        points = check_points(data["raw_points"], path, "raw_points", allow_empty=False)
        count = len(points)
        for key in PER_POINT:
            if data[key].shape != (count,):
                raise fail(path, f"{key} must have shape ({count},) like raw_points, got {data[key].shape}")
        time = data["time_indice"]
        if not np.array_equal(time, np.round(time)):
            raise fail(path, "time_indice must hold whole frame numbers")
        time = time.astype(np.int64)
        inst = data["inst_labels"].astype(np.int64)
        for key in ("fb_labels", "sd_labels"):
            if not np.isin(data[key], (0, 1)).all():
                raise fail(path, f"{key} must hold only 0 and 1")
        classes = self._classes(path, data)
        ego, boxes = data["ego_motion_gt"].astype(np.float64), data["bbox_tsfm"].astype(np.float64)
        frames = self.frames
        if ego.shape != (frames, 4, 4):
            raise fail(path, f"ego_motion_gt must have shape ({frames}, 4, 4) for {frames} frames, got {ego.shape}")
        if boxes.ndim != 4 or boxes.shape[1:] != (frames, 4, 4):
            raise fail(path, f"bbox_tsfm must have shape (K, {frames}, 4, 4), got {boxes.shape}")
        present = np.bincount(time, minlength=frames) if time.min() >= 0 else None
        if present is None or len(present) != frames or not present.all():
            raise fail(path, f"time_indice must cover frames 0..{frames - 1}, each non-empty")
        if inst.min() < 0 or inst.max() >= len(boxes):
            raise fail(path, f"inst_labels must lie in 0..{len(boxes) - 1} (bbox_tsfm has {len(boxes)} instances)")
        order = [frames - 1 - t for t in range(frames)]  # scan t of the sequence is frame c = F - 1 - t
        masks = [time == c for c in order]
        object_poses = {}
        for k in np.unique(inst[inst > 0]):
            poses = np.tile(np.eye(4), (frames, 1, 1))  # the anchor's: no motion into itself
            for t, c in enumerate(order[:-1]):
                problem = rigid_problem(boxes[k, c])
                if problem and np.any(inst[masks[t]] == k):
                    raise fail(path, f"bbox_tsfm[{k}, {c}] {problem}")
                if not problem:  # else the instance is absent there: identity, never used by pairs into the anchor
                    poses[t] = invert(boxes[k, c])
            object_poses[int(k)] = poses
        sequence = FrameSequence(
            points=[points[m] for m in masks],
            poses=ego[order],
            timestamps_ns=np.round(np.arange(frames) * 1e9 / self.frequency_hz).astype(np.int64),
            classes=[classes[m] for m in masks],
            instance=[inst[m].astype(np.int32) for m in masks],
            object_poses=object_poses,
            log_id=self.sample_id(index),
            source=str(path),
        )
        return sequence, [data["sd_labels"][m].astype(bool) for m in masks]

    def _classes(self, path: Path, data: dict[str, np.ndarray]) -> np.ndarray:
        """(m,) int32 project classes of every stacked point (see the module docstring)."""
        foreground = data["fb_labels"] == 1
        if self.sem_labels == "nuscenes":
            return foreground.astype(np.int32)
        sem = data["sem_labels"]
        if sem.shape != foreground.shape:
            raise fail(path, f"sem_labels must have shape {foreground.shape} like raw_points, got {sem.shape}")
        bad = foreground & ~np.isin(sem, list(WAYMO_CLASSES))
        if bad.any():
            raise fail(
                path,
                f"{int(bad.sum())} foreground points (fb_labels 1) have sem_labels outside 0 (vehicle), "
                "1 (pedestrian), 3 (cyclist)",
            )
        table = np.zeros(max(WAYMO_CLASSES) + 1, np.int32)
        table[list(WAYMO_CLASSES)] = list(WAYMO_CLASSES.values())
        classes = np.zeros(len(sem), np.int32)
        classes[foreground] = table[sem[foreground].astype(np.int64)]
        return classes
