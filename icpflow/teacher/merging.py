"""Step 8b (extension for long, fast vehicles): recombine the clusters of one rigid object the clustering split.

HDBSCAN clusters both scans fused; a long vehicle moving fast overlaps itself and is often cut at a fixed place in
space, so one label holds the rear of the object in pc0 and its middle in pc1, the other the rest. Neither part
registers well on its own: one slides onto the other scan's part (a false static match) and the other fails the
checks, and the whole vehicle gets a wrong flow. The reference has no such step (measured: BENCHMARKS.md, "Teacher:
speed and quality").

Candidates: two labels are adjacent when their bounding boxes over both scans come within ``merging.distance``
metres and points of the two (either scan) fall in the same or neighbouring cells of that size; an adjacent pair is
a candidate when at least one of them is unmatched (with at least ``clustering.min_cluster_size`` source points) or
matched with a motion (a match at the identity on both sides is left alone: static structure), and the union of their
source points is at most ``merging.max_extent`` long along its main horizontal axis. The union of both labels'
points in both scans (plus the pc1 clusters they were matched to) is registered like any candidate pair (the
pipeline's histogram, ICP, static preference and checks). It is kept when it passes and its symmetric error (the
mean of both directions' mean nearest-neighbour distances: the smaller one alone cannot see a part of one scan that
nothing covers) is below ``(1 - merging.gain)`` times that of the parts as they stand, measured the same way on the
same points (each part moved by its own match, an unmatched part not moved). Kept merges are applied greedily,
largest gain first, each label merged once per round, for ``merging.rounds`` rounds (a vehicle cut in three needs
two). The test registers at most ``merging.test_points`` points per cluster; the kept merges are registered again on
all of ``icp.max_points`` (that registration replaces the test's where it passes the checks).

Points: source (Ns, 3) (pc0 ego-compensated into pc1's frame) and destination (Nd, 3), one frame; labels (N,)
int32 fused ids, -1 for none. Matches: the pipeline's arrays (``pairs`` (M, 2) src/dst label, ``transforms`` (M, 4,
4), ``errors``, ``iou_ratios``, ``match_confidence``, ``stage`` (M,)); a merged match has stage 3.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from icpflow.core.geometry import transform_points
from icpflow.teacher import registration
from icpflow.teacher.config import ICPConfig, MergingConfig
from icpflow.teacher.histogram import main_axis
from icpflow.teacher.pairing import ClusterStats, cluster_stats

MERGED_STAGE = 3


def adjacent_labels(points: np.ndarray, labels: np.ndarray, distance: float, pairs: np.ndarray) -> np.ndarray:
    """The label pairs of ``pairs`` (K, 2) whose points (N, 3), labels (N,) fall in the same or neighbouring
    cubic cells of ``distance`` metres: (K', 2) int64, each row sorted (a < b), unique."""
    pairs = np.unique(np.sort(np.asarray(pairs, np.int64).reshape(-1, 2), axis=1), axis=0)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    keep = np.isin(labels, pairs)
    if len(pairs) == 0 or not keep.any():
        return np.zeros((0, 2), np.int64)
    cells = np.floor(points[keep] / distance).astype(np.int64)
    cells -= cells.min(axis=0) - 1  # one empty cell of margin on every side: neighbours never wrap around
    span = cells.max(axis=0) + 2
    n_labels = int(labels.max()) + 1
    # one sorted int64 per occupied (cell, label): the cell's index times the label count, plus the label
    occupied = np.unique(((cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]) * n_labels + labels[keep])
    keys, owners = occupied // n_labels, occupied % n_labels
    found = []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                shifted = keys + (dx * span[1] + dy) * span[2] + dz
                at = np.searchsorted(keys, shifted)
                # every occupant of the neighbouring cell: walk the run of equal keys from the first one
                while True:
                    hit = (at < len(keys)) & (keys[np.minimum(at, len(keys) - 1)] == shifted)
                    if not hit.any():
                        break
                    rows = np.flatnonzero(hit)
                    found.append(np.column_stack([owners[rows], owners[at[rows]]]))
                    at = np.where(hit, at + 1, len(keys))
    touching = np.concatenate(found)
    touching = np.unique(np.sort(touching[touching[:, 0] != touching[:, 1]], axis=1), axis=0)
    code = lambda rows: rows[:, 0] * n_labels + rows[:, 1]  # noqa: E731
    return pairs[np.isin(code(pairs), code(touching))]


def _box_neighbours(src_stats, dst_stats, active: np.ndarray, distance: float) -> np.ndarray:
    """(K, 2) label pairs with at least one ``active`` label whose bounding boxes over both scans come within
    ``distance`` metres of each other."""
    lower = np.minimum(src_stats.lower, dst_stats.lower)
    upper = np.maximum(src_stats.upper, dst_stats.upper)
    present = np.flatnonzero(np.isfinite(lower).all(axis=1))
    first = present[active[present]]
    if len(first) == 0:
        return np.zeros((0, 2), np.int64)
    gap = np.maximum(lower[None, present] - upper[first, None], lower[first, None] - upper[None, present])
    near = (gap <= distance).all(axis=2)
    a, b = np.nonzero(near)
    return np.column_stack([first[a], present[b]])


def _moved_parts(src: np.ndarray, src_stats: ClusterStats, parts: list[int], transform_of: dict) -> np.ndarray:
    """Source points of the labels ``parts``, each moved by its match's transform (the identity if none)."""
    out = []
    for label in parts:
        out.append(transform_points(transform_of.get(label, np.eye(4)), src_stats.points(src, label)))
    return np.concatenate(out)


def merge_split_clusters(
    src: np.ndarray,
    dst: np.ndarray,
    src_labels: np.ndarray,
    dst_labels: np.ndarray,
    src_stats: ClusterStats,
    dst_stats: ClusterStats,
    matches: dict,
    register: Callable[[list, np.ndarray, int | None], dict],
    cfg: MergingConfig,
    icp: ICPConfig,
    min_cluster_size: int,
    seed: int = 0,
) -> tuple[int, ClusterStats, ClusterStats]:
    """Merge split clusters (see the module docstring); ``src_labels``, ``dst_labels`` and ``matches`` are updated
    in place. ``src_stats``/``dst_stats``: the scans' ``pairing.ClusterStats`` of labels 0 .. L-1.
    ``register(clouds, src_centroids, max_points)`` registers candidate pairs as the pipeline does (ICP on at most
    ``max_points`` points per cluster; None: the ICP's own cap) and returns their
    ``transforms``, ``errors``, ``symmetric_errors``, ``iou_ratios``, ``match_confidence`` and ``passed``
    (checks). Returns (merges applied, the statistics of the merged labels)."""
    if cfg.distance <= 0:
        return 0, src_stats, dst_stats
    merged = 0
    measure = dataclasses.replace(icp, max_iter=0, max_points=min(icp.max_points, cfg.test_points))
    n_labels = len(src_stats.count)
    for _ in range(cfg.rounds):
        moving = {int(s): t for (s, _), t in zip(matches["pairs"], matches["transforms"])}
        partner = {int(s): int(d) for s, d in matches["pairs"]}
        # unmatched with enough source points to have been paired, matched with a motion, or matched at the
        # identity with a poor overlap (a part of a long vehicle sliding along itself)
        active = src_stats.count >= min_cluster_size
        for label, t, iou in zip(matches["pairs"][:, 0], matches["transforms"], matches["iou_ratios"]):
            active[label] = not np.array_equal(t, np.eye(4)) or iou < cfg.static_iou
        near = _box_neighbours(src_stats, dst_stats, active, cfg.distance)
        adjacent = adjacent_labels(
            np.concatenate([src, dst]), np.concatenate([src_labels, dst_labels]), cfg.distance, near
        )
        candidates, clouds, parts_clouds, centroids = [], [], [], []
        for a, b in adjacent:
            group = [int(a), int(b)]
            source = np.concatenate([src_stats.points(src, g) for g in group])
            dst_group = sorted({*group, *(partner[g] for g in group if g in partner)})
            target = np.concatenate([dst_stats.points(dst, g) for g in dst_group])
            if len(source) < min_cluster_size or len(target) < min_cluster_size:
                continue
            if main_axis(source)[1] > cfg.max_extent:
                continue
            candidates.append((group, dst_group))
            clouds.append((source, target))
            parts_clouds.append((_moved_parts(src, src_stats, group, moving), target))
            centroids.append(source.mean(axis=0))
        if not candidates:
            break
        result = register(clouds, np.array(centroids), cfg.test_points)
        parts = registration.register_clusters(parts_clouds, np.tile(np.eye(4), (len(candidates), 1, 1)), measure, seed)
        merged_error, parts_error = result["symmetric_errors"], parts.symmetric_error
        gain = parts_error - merged_error
        good = np.flatnonzero(result["passed"] & (merged_error < (1.0 - cfg.gain) * parts_error))
        chosen, used = [], set()
        for k in good[np.argsort(-gain[good], kind="stable")]:
            group, dst_group = candidates[k]
            if not used & {*group, *dst_group}:
                used |= {*group, *dst_group}
                chosen.append(k)
        if not chosen:
            break
        # the kept merges registered again on all of icp.max_points (the test above used cfg.test_points)
        full = register([clouds[k] for k in chosen], np.array([centroids[k] for k in chosen]), None)
        for row, k in enumerate(chosen):
            if full["passed"][row]:
                for key in ("transforms", "errors", "iou_ratios", "match_confidence"):
                    result[key][k] = full[key][row]
        for k in chosen:
            group, dst_group = candidates[k]
            keep, absorbed = group[0], group[1:]
            src_labels[np.isin(src_labels, absorbed)] = keep
            dst_labels[np.isin(dst_labels, absorbed)] = keep
            drop = np.isin(matches["pairs"][:, 0], group)
            for key in ("pairs", "transforms", "errors", "iou_ratios", "match_confidence", "stage"):
                matches[key] = matches[key][~drop]
            matches["pairs"] = np.concatenate([matches["pairs"], np.array([[keep, keep]], np.int32)])
            matches["transforms"] = np.concatenate([matches["transforms"], result["transforms"][k][None]])
            matches["errors"] = np.concatenate([matches["errors"], [result["errors"][k]]])
            matches["iou_ratios"] = np.concatenate([matches["iou_ratios"], [result["iou_ratios"][k]]])
            matches["match_confidence"] = np.concatenate(
                [matches["match_confidence"], result["match_confidence"][k : k + 1]]
            )
            matches["stage"] = np.concatenate([matches["stage"], np.array([MERGED_STAGE], np.int8)])
        merged += len(chosen)
        src_stats, dst_stats = cluster_stats(src, src_labels, n_labels), cluster_stats(dst, dst_labels, n_labels)
    return merged, src_stats, dst_stats
