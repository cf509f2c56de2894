"""Step 7: reject implausible cluster registrations.

A pair fails when any of these holds (thresholds: ``icpflow.teacher.config.ChecksConfig``):

* its displacement is longer than the search window (``window``, metres, per pair). The displacement is that of
  the source cluster's centroid, ``T c - c``, when centroids are given (the reference's choice: it does not grow
  with the cluster's distance from the origin as the rotation is applied), else the translation part of ``T``;
* its IoU ratio is below ``min_iou`` (0.2);
* its |roll| or |pitch| exceeds ``max_roll_pitch_deg`` (9 degrees): objects on the road do not tip over;
* its mean error exceeds ``max_error`` (0.2 m; 0.3 m Waymo);
* any of its numbers is not finite.
"""

from __future__ import annotations

import numpy as np

from icpflow.core.geometry import euler_angles
from icpflow.teacher.config import ChecksConfig


def passes(
    transforms: np.ndarray,
    mean_error: np.ndarray,
    iou_ratio: np.ndarray,
    window: np.ndarray,
    cfg: ChecksConfig,
    *,
    src_centroids: np.ndarray | None = None,
) -> np.ndarray:
    """(P,) bool: which of P registrations pass every check.

    transforms (P, 4, 4) src -> dst; mean_error (P,) metres; iou_ratio (P,); window (P,) or scalar metres;
    src_centroids (P, 3) optional.
    """
    transforms = np.asarray(transforms, dtype=np.float64).reshape(-1, 4, 4)
    n_pairs = len(transforms)
    mean_error = np.asarray(mean_error, dtype=np.float64).reshape(-1)
    iou_ratio = np.asarray(iou_ratio, dtype=np.float64).reshape(-1)
    window = np.broadcast_to(np.asarray(window, dtype=np.float64), (n_pairs,))
    if len(mean_error) != n_pairs or len(iou_ratio) != n_pairs:
        raise ValueError(f"passes: {n_pairs} transforms but {len(mean_error)} errors and {len(iou_ratio)} IoU ratios")

    if src_centroids is None:
        displacement = transforms[:, :3, 3]
    else:
        centroids = np.asarray(src_centroids, dtype=np.float64).reshape(n_pairs, 3)
        displacement = np.einsum("pij,pj->pi", transforms[:, :3, :3], centroids) + transforms[:, :3, 3] - centroids
    angles = np.array([euler_angles(t)[:2] for t in transforms]).reshape(n_pairs, 2)
    finite = np.isfinite(transforms).all(axis=(1, 2)) & np.isfinite(mean_error) & np.isfinite(iou_ratio)
    with np.errstate(invalid="ignore"):
        ok = (
            finite
            & (np.linalg.norm(displacement, axis=1) <= window)
            & (iou_ratio >= cfg.min_iou)
            & (np.abs(np.degrees(angles)).max(axis=1, initial=0.0) <= cfg.max_roll_pitch_deg)
            & (mean_error <= cfg.max_error)
        )
    return ok
