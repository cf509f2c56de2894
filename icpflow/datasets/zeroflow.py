"""Argoverse 2 as dumped by the ZeroFlow pipeline: the ICP-Flow reference's AV2 input.

Layout: ``<root>/<split>_zero_flow/<log_id>/<index>.npz``, each with

* ``pc1`` (M0, 3), ``pc2`` (M1, 3): the two sweeps, NaN-padded to a fixed size, already ego-compensated (both in
  one common frame) and ground-removed;
* ``pc1_flows_valid_idx``, ``pc2_flows_valid_idx``: the rows to keep (integer indices or boolean masks);
* ``gt_flow_0_1`` (M0, 3): ground-truth flow of ``pc1`` rows in that common frame (ego motion already removed);
* ``pc1_classes`` (M0,): -1 background, else the 0-based AV2 category; optional ``ground1``/``ground2`` masks.

What a pair holds: the dump carries no ego pose, so the common frame stands for both ego frames:
``ego1_from_ego0`` is the identity, ``pc0``/``pc1`` are the kept rows as given, and ``flow`` is
``gt_flow_0_1`` as given, so ``pc0 + flow`` lies in pc1's frame and the flow is at once full and residual.
Padding rows (NaN points) must lie outside the valid rows, which alone are read: a NaN or Inf point or flow
among the valid rows is an error. ``classes`` = ``pc1_classes + 1`` (int32, 0 = none, else AV2 category index
+ 1, as the AV2 reader); ``dynamic`` = flow of at least 0.05 m per 0.1 s (0.5 m/s); ``ground0``/``ground1`` from
the dump's masks when present, else all False (the dump is ground-removed); ``dt`` = 0.1 s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from icpflow.core.classes import AV2_META
from icpflow.core.frame_pair import FramePair, check_points
from icpflow.datasets.base import IndexedDataset
from icpflow.datasets.file_formats import fail, load_npz

KEYS = ("pc1", "pc2", "gt_flow_0_1", "pc1_flows_valid_idx", "pc2_flows_valid_idx", "pc1_classes")
#: the AV2 dynamic rule, as the AV2 reader: at least 0.05 m between sweeps 0.1 s apart
DYNAMIC_METRES = 0.05
NUM_CATEGORIES = 30


def _kept_rows(path, name: str, points: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Row indices selected by ``valid`` (indices or mask); every selected point must be finite."""
    check_points(points, path, name, finite=False)  # numeric, not transposed; padding rows may be NaN (below)
    if points.shape[1] != 3:  # gt_flow_0_1 has pc1's shape
        raise fail(path, f"{name} must have shape (M, 3), got {points.shape}")
    if valid.dtype == np.bool_:
        if valid.shape != (len(points),):
            raise fail(path, f"{name}_flows_valid_idx mask must have shape ({len(points)},), got {valid.shape}")
        rows = np.flatnonzero(valid)
    elif np.issubdtype(valid.dtype, np.integer) and valid.ndim == 1:
        if len(valid) and (valid.min() < 0 or valid.max() >= len(points)):
            raise fail(path, f"{name}_flows_valid_idx has indices outside 0..{len(points) - 1}")
        rows = valid.astype(np.int64)
    else:
        raise fail(path, f"{name}_flows_valid_idx must be 1-D integer indices or a bool mask, got {valid.dtype}")
    if len(rows) == 0:
        raise fail(path, f"{name} has no valid points")
    bad = int((~np.isfinite(points[rows])).any(axis=1).sum())
    if bad:
        raise fail(
            path,
            f"{name} has {bad} NaN or Inf rows among its {len(rows)} valid rows "
            f"({name}_flows_valid_idx must leave out the padding)",
        )
    return rows


class ZeroFlowAV2Dataset(IndexedDataset):
    """ZeroFlow dumps of Argoverse 2 pairs (see the module docstring for frames and conversions)."""

    name = "zeroflow_av2"
    class_to_meta = AV2_META

    def __init__(self, root: str | Path, split: str = "val", subdir: str = "{split}_zero_flow") -> None:
        self.root = Path(root)
        self.split = split
        folder = self.root / subdir.format(split=split)
        self._index_files(sorted(folder.glob("*/*.npz")))
        if not self.files:
            raise fail(folder, "no <log_id>/<index>.npz files")

    def _file_id(self, path: Path) -> str:
        return f"{path.parent.name}/{path.stem}"

    def metadata(self) -> dict:
        return {**super().metadata(), "root": str(self.root), "split": self.split}

    def pair(self, index: int, horizon: int = 1) -> FramePair:
        if horizon != 1:
            raise IndexError(f"{self.name}: only horizon 1 exists in ZeroFlow dumps, got {horizon}")
        path = self.files[index]
        data = load_npz(path, KEYS, optional=("ground1", "ground2"))
        pc1, pc2, flow = data["pc1"], data["pc2"], data["gt_flow_0_1"]
        rows0 = _kept_rows(path, "pc1", pc1, data["pc1_flows_valid_idx"])
        rows1 = _kept_rows(path, "pc2", pc2, data["pc2_flows_valid_idx"])
        if flow.shape != pc1.shape:
            raise fail(path, f"gt_flow_0_1 must have the shape of pc1 {pc1.shape}, got {flow.shape}")
        flow = flow[rows0].astype(np.float32)
        if not np.isfinite(flow).all():
            bad = int((~np.isfinite(flow)).any(axis=1).sum())
            raise fail(path, f"gt_flow_0_1 has NaN or Inf at {bad} valid points")
        classes = data["pc1_classes"]
        if classes.shape != (len(pc1),) or not np.issubdtype(classes.dtype, np.integer):
            got = f"{classes.dtype} {classes.shape}"
            raise fail(path, f"pc1_classes must be integers of shape ({len(pc1)},), got {got}")
        classes = classes[rows0].astype(np.int32) + 1
        if classes.min() < 0 or classes.max() > NUM_CATEGORIES:
            raise fail(path, f"pc1_classes must lie in -1..{NUM_CATEGORIES - 1}")
        ground = []
        for key, points, rows in (("ground1", pc1, rows0), ("ground2", pc2, rows1)):
            mask = data.get(key)
            if mask is not None and mask.shape != (len(points),):
                raise fail(path, f"{key} must have shape ({len(points)},), got {mask.shape}")
            ground.append(np.zeros(len(rows), bool) if mask is None else mask[rows].astype(bool))
        return FramePair(
            pc0=pc1[rows0].astype(np.float32),
            pc1=pc2[rows1].astype(np.float32),
            ego1_from_ego0=np.eye(4),
            ground0=ground[0],
            ground1=ground[1],
            flow=flow,
            flow_valid=np.ones(len(rows0), bool),
            classes=classes,
            dynamic=np.linalg.norm(flow, axis=1) >= DYNAMIC_METRES,
            dt=0.1,
            log_id=path.parent.name,
            sample_id=self.sample_id(index),
            source=str(path),
        )
