"""Steps 9 and 10: per-point flow and confidence from the matched clusters.

Flow of a pc0 point p (its own ego frame): ``(T_cluster @ T_ego) p - p`` if its cluster is matched, where
``T_cluster`` moves the cluster within pc1's frame after ego compensation by ``T_ego = ego1_from_ego0``; else the
ego flow ``T_ego p - p`` (unmatched, unclustered, ground, cropped points).

Confidence of a matched cluster (0 elsewhere), in [0, 1]:

    confidence = clip(1 - error / max_error, 0, 1) * clip(iou / conf_iou_full, 0, 1)

with ``max_error`` the checks' (``ChecksConfig``) and ``conf_iou_full`` a ``FlowConfig`` field. ``error`` is the
match's mean nearest-neighbour distance (m), ``iou`` its IoU ratio; a perfect registration (error 0,
IoU >= conf_iou_full) scores 1, one at the acceptance limit (error = max_error) scores 0.

Optional extension (``absorb_radius`` > 0, off in the reference): a ground or unclustered pc0 point within
``absorb_radius`` of a point of a matched cluster moves (and is trusted) with that cluster. It recovers the lowest
parts of vehicles that ground removal cut off and HDBSCAN's noise around objects.
"""

from __future__ import annotations

import numpy as np

from icpflow.core.geometry import ego_flow, transform_points
from icpflow.teacher.config import FlowConfig


def match_confidence(error: np.ndarray, iou: np.ndarray, cfg: FlowConfig, max_error: float) -> np.ndarray:
    """(M,) float32 confidence of M matches from their errors and IoU ratios (formula above)."""
    error = np.asarray(error, dtype=np.float64)
    iou = np.asarray(iou, dtype=np.float64)
    quality = np.clip(1.0 - error / max_error, 0.0, 1.0) * np.clip(iou / cfg.conf_iou_full, 0.0, 1.0)
    return np.nan_to_num(quality, nan=0.0).astype(np.float32)


def absorb(pc0, labels0, ego1_from_ego0, matched_src, radius: float, eligible) -> np.ndarray:
    """(N0,) int32 labels where each unlabelled, ``eligible`` pc0 point takes the label of the nearest point of a
    matched cluster within ``radius`` metres (positions compared after ego compensation, i.e. in pc1's frame)."""
    from scipy.spatial import cKDTree

    labels = labels0.copy()
    members = np.flatnonzero(np.isin(labels0, matched_src))
    free = np.flatnonzero((labels0 < 0) & eligible)
    if len(members) == 0 or len(free) == 0:
        return labels
    transform = np.asarray(ego1_from_ego0, np.float64)
    tree = cKDTree(transform_points(transform, np.asarray(pc0[members], np.float64)))
    query = transform_points(transform, np.asarray(pc0[free], np.float64))
    distance, nearest = tree.query(query, distance_upper_bound=radius)
    hit = np.isfinite(distance)
    labels[free[hit]] = labels0[members[nearest[hit]]]
    return labels


def point_flow(
    pc0: np.ndarray,
    labels0: np.ndarray,
    ego1_from_ego0: np.ndarray,
    matched_src: np.ndarray,
    transforms: np.ndarray,
    confidences: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Full flow (N0, 3) float32 and confidence (N0,) float32 of pc0 (N0, 3) with cluster labels (N0,) int32.

    ``matched_src`` (M,) source cluster ids, ``transforms`` (M, 4, 4) their motions in pc1's frame,
    ``confidences`` (M,).
    """
    flow = ego_flow(pc0, ego1_from_ego0)
    confidence = np.zeros(len(pc0), dtype=np.float32)
    if len(matched_src) == 0 or len(pc0) == 0:
        return flow, confidence
    slot = np.full(max(int(labels0.max(initial=-1)), int(np.max(matched_src))) + 2, -1, dtype=np.int64)
    slot[np.asarray(matched_src) + 1] = np.arange(len(matched_src))
    which = slot[labels0 + 1]
    rows = np.flatnonzero(which >= 0)
    totals = np.asarray(transforms, np.float64) @ ego1_from_ego0  # (M, 4, 4): pc0 frame -> moved, pc1 frame
    total = totals[which[rows]]
    points = pc0[rows].astype(np.float64)
    moved = np.einsum("nij,nj->ni", total[:, :3, :3], points) + total[:, :3, 3]
    flow[rows] = (moved - points).astype(np.float32)
    confidence[rows] = np.asarray(confidences, np.float32)[which[rows]]
    return flow, confidence
