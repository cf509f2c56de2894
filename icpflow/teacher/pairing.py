"""Step 4: candidate cluster pairs.

Clusters come from one fused clustering, so a label may own points of both scans. Stage 1 pairs each label with
itself (likely static objects); stage 2 pairs the source and destination clusters left unmatched by stage 1,
every combination. Both stages keep a pair only if (the reference's sanity check):

* both clusters have at least ``clustering.min_cluster_size`` points;
* the xy distance of their centroids is at most the window ``2 * max(speed * k, |t_ego|)``;
* each ratio of their sorted bounding-box extents (smaller / larger, per rank) is at least ``extent_ratio``.

Points: source (pc0, ego-compensated into pc1's frame) and destination (pc1), both (N, 3); labels (N,) int32.
Settings: ``icpflow.teacher.config.PairingConfig`` (the window: ``PairingConfig.window``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from icpflow.teacher.config import PairingConfig


@dataclass
class ClusterStats:
    """Per-label statistics of one scan for labels 0 .. L-1: ``count`` (L,), ``centroid`` (L, 3), ``extent`` (L, 3)
    sorted bounding-box side lengths (ascending), ``order``/``starts`` to slice each label's points, ``lower``/
    ``upper`` (L, 3) the axis-aligned bounding box's corners (+inf / -inf for a label with no point)."""

    count: np.ndarray
    centroid: np.ndarray
    extent: np.ndarray
    order: np.ndarray
    starts: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    def points(self, points: np.ndarray, label: int) -> np.ndarray:
        """(n, 3) points of ``label``."""
        return points[self.order[self.starts[label] : self.starts[label + 1]]]


def cluster_stats(points: np.ndarray, labels: np.ndarray, n_labels: int) -> ClusterStats:
    """Statistics of labels 0 .. n_labels-1 (label -1 ignored) of (N, 3) points."""
    valid = np.flatnonzero(labels >= 0)
    order = valid[np.argsort(labels[valid], kind="stable")]
    count = np.bincount(labels[valid], minlength=n_labels)[:n_labels]
    starts = np.concatenate([[0], np.cumsum(count)])
    centroid = np.zeros((n_labels, 3))
    lower = np.full((n_labels, 3), np.inf)
    upper = np.full((n_labels, 3), -np.inf)
    present = count > 0
    if len(order):  # the points sorted by label: one contiguous segment per present label
        sorted_points = points[order].astype(np.float64)
        begins = starts[:-1][present]
        centroid[present] = np.add.reduceat(sorted_points, begins, axis=0)
        lower[present] = np.minimum.reduceat(sorted_points, begins, axis=0)
        upper[present] = np.maximum.reduceat(sorted_points, begins, axis=0)
    centroid[present] /= count[present, None]
    extent = np.where(present[:, None], upper - lower, 0.0)
    return ClusterStats(count, centroid, np.sort(extent, axis=1), order, starts, lower, upper)


def plausible(
    src: ClusterStats, dst: ClusterStats, src_ids, dst_ids, window: float, cfg: PairingConfig, min_cluster_size: int
) -> np.ndarray:
    """(P,) bool: which pairs (src_ids[p], dst_ids[p]) pass the sanity check above."""
    src_ids = np.asarray(src_ids, dtype=np.int64)
    dst_ids = np.asarray(dst_ids, dtype=np.int64)
    big_enough = (src.count[src_ids] >= min_cluster_size) & (dst.count[dst_ids] >= min_cluster_size)
    distance = np.linalg.norm(src.centroid[src_ids, :2] - dst.centroid[dst_ids, :2], axis=1)
    a, b = src.extent[src_ids], dst.extent[dst_ids]
    larger = np.maximum(a, b)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(larger > 0, np.minimum(a, b) / larger, 1.0)
    return big_enough & (distance <= window) & (ratio >= cfg.extent_ratio).all(axis=1)


def stage1_pairs(
    src: ClusterStats, dst: ClusterStats, window: float, cfg: PairingConfig, min_cluster_size: int
) -> tuple[np.ndarray, np.ndarray]:
    """Same-label candidate pairs: (src_ids, dst_ids) int64."""
    ids = np.flatnonzero((src.count > 0) & (dst.count > 0))
    keep = plausible(src, dst, ids, ids, window, cfg, min_cluster_size)
    return ids[keep], ids[keep]


def stage2_pairs(
    src: ClusterStats,
    dst: ClusterStats,
    src_free: np.ndarray,
    dst_free: np.ndarray,
    window: float,
    cfg: PairingConfig,
    min_cluster_size: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Every plausible (src, dst) among the labels not matched in stage 1: (src_ids, dst_ids) int64."""
    src_ids = np.flatnonzero(src_free & (src.count >= min_cluster_size))
    dst_ids = np.flatnonzero(dst_free & (dst.count >= min_cluster_size))
    s, d = np.repeat(src_ids, len(dst_ids)), np.tile(dst_ids, len(src_ids))
    keep = plausible(src, dst, s, d, window, cfg, min_cluster_size)
    return s[keep], d[keep]
