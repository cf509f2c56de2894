"""Step 3: one HDBSCAN over the fused non-ground points of both scans (pc0 already ego-compensated).

Labels: -1 for noise, else 0 .. K-1 with 0 the largest cluster; only the ``max_clusters`` largest are kept.
Optional voxel down-sampling (``voxel_size`` > 0): one point (the voxel mean) per occupied voxel is clustered
and every point takes its voxel's label. Settings: ``icpflow.teacher.config.ClusteringConfig``.
"""

from __future__ import annotations

import numpy as np

from icpflow.teacher.config import ClusteringConfig
from icpflow.teacher.hdbscan_labels import hdbscan_labels


def voxel_downsample(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """(M, 3) float32 voxel means of (N, 3) points and the (N,) index of each point's voxel (voxels sorted by key)."""
    cells = np.floor(points / voxel).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    means = np.stack([np.bincount(inverse, weights=points[:, a], minlength=len(counts)) for a in range(3)], axis=1)
    return (means / counts[:, None]).astype(np.float32), inverse


def cluster_points(points: np.ndarray, cfg: ClusteringConfig) -> np.ndarray:
    """(N,) int32 cluster labels of (N, 3) fused points (see module docstring)."""
    n = len(points)
    labels = np.full(n, -1, dtype=np.int32)
    if n < cfg.min_cluster_size:
        return labels
    if cfg.voxel_size > 0:
        reduced, inverse = voxel_downsample(points, cfg.voxel_size)
    else:
        reduced, inverse = points, None
    if len(reduced) < 2:
        return labels
    min_size = max(2, min(cfg.min_cluster_size, len(reduced)))
    raw = hdbscan_labels(
        reduced,
        min_cluster_size=min_size,
        min_samples=min(cfg.min_samples or min_size, len(reduced) - 1),
        epsilon=float(cfg.epsilon),
        leaf_size=cfg.leaf_size,
        workers=cfg.n_jobs,
    )
    if inverse is not None:
        raw = raw[inverse]
    return relabel_by_size(raw, cfg.max_clusters)


def relabel_by_size(raw: np.ndarray, max_clusters: int) -> np.ndarray:
    """Labels 0 .. K-1 by decreasing size (ties: smaller raw label first), K <= max_clusters; the rest -1."""
    labels = np.full(len(raw), -1, dtype=np.int32)
    valid = raw >= 0
    if not valid.any():
        return labels
    ids, inverse, counts = np.unique(raw[valid], return_inverse=True, return_counts=True)
    order = np.lexsort((ids, -counts))[:max_clusters]
    mapping = np.full(len(ids), -1, dtype=np.int32)
    mapping[order] = np.arange(len(order), dtype=np.int32)
    labels[valid] = mapping[inverse.reshape(-1)]
    return labels
