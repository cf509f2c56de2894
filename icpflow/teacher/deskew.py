"""Step 6b (extension, ``deskew``): rolling-shutter refinement of moving cluster matches.

A spinning LiDAR captures a scan over about 0.1 s, so a moving object is smeared along its velocity: a point
captured ``tau`` seconds after the scan's timestamp lies ``v * tau`` further along than the object was at the
timestamp. On Argoverse 2 the two stacked lidars scan with different phases, so one car can be captured 50 ms
apart by the two, 0.4 m at 8 m/s, and ICP between two such smeared clusters lands short.

For each matched pair whose registration moves the source centroid by at least ``deskew.min_speed * dt``:

1. velocity ``v`` in pc1's frame. The clusters' mean capture times differ by ``lag = mean(time1) - mean(time0)``
   (e.g. an object that crosses the sweep's start azimuth between the scans), so the apparent displacement of the
   centroids is ``v * (dt + lag)``, not ``v * dt``: ``v = (s + v_prev * lag) / (dt + lag)`` with ``s`` the
   centroid displacement of the current transform ``T`` between the clusters as de-skewed with ``v_prev`` (0 at
   first); ``dt + lag`` is kept >= ``dt / 4`` (an object seen at the end of one sweep and the start of the next
   barely moves between them, and dividing by that gap would amplify noise). ``T``'s translation is shifted so
   that it moves the centroid by ``v * dt``;
2. de-skew both clusters to their scan's timestamp: ``p - v * time0`` (source, pc0 ego-compensated) and
   ``q - v * time1`` (destination, pc1), ``time0``/``time1`` each point's capture time after its own scan's
   timestamp (``FramePair.time0``/``time1``);
3. re-register the de-skewed clusters starting from ``T`` with point-to-plane ICP (``registration.register_plane``:
   rotation about z and translation; numba on the CPU whatever ``icp_backend`` says, these are few pairs);

repeated ``deskew.iters`` times (v follows the refined ``T``). The refined ``T`` is kept when it passes the
checks (``checks``), with its error and IoU ratio measured on the de-skewed clusters; otherwise the first
registration stays. Only the translation is de-skewed (rotation during one sweep is ignored).

What the result means: ``T`` maps the object as it was at scan 0's timestamp to where it is at scan 1's
timestamp, i.e. the rigid motion between the two timestamps, which is what box-based ground truth (Argoverse 2's
boxes are annotated at the sweep timestamps) gives. The flow is still ``(T @ T_ego) p - p`` applied to the
ORIGINAL pc0 points (project convention: ``pc0 + flow`` is in pc1's frame); it is not the flow of de-skewed
positions. The motion between timestamps is the same for every point of a rigid object whatever its capture
time, so the flow does not depend on ``time0``; only the estimate of ``T`` does.
"""

from __future__ import annotations

import numpy as np

from icpflow.teacher import checks, registration
from icpflow.teacher.config import ICPFlowConfig
from icpflow.teacher.flow import match_confidence


def refine(
    src, dst, src_stats, dst_stats, time_src, time_dst, matches: dict, dt: float, window: float, cfg: ICPFlowConfig
) -> int:
    """De-skew and re-register the moving matches in ``matches`` (updated in place); returns how many changed.

    ``src`` (Ns, 3) source points in pc1's frame and ``dst`` (Nd, 3), with ``time_src`` (Ns,) / ``time_dst``
    (Nd,) seconds after their scan's timestamp; ``src_stats``/``dst_stats`` their ``pairing.ClusterStats``;
    ``matches`` the pipeline's arrays (``pairs`` (M, 2), ``transforms`` (M, 4, 4), ``errors``, ``iou_ratios``,
    ``match_confidence`` (M,)); ``dt`` seconds between the scans; ``window`` metres (the checks' limit); ``cfg``
    the teacher's settings (its ``deskew``, ``icp``, ``checks`` and ``flow`` blocks and ``seed``).
    """
    pairs = matches["pairs"]
    if len(pairs) == 0:
        return 0
    centroids = src_stats.centroid[pairs[:, 0]]
    transforms = np.asarray(matches["transforms"], np.float64)
    moving = np.flatnonzero(_displacement(transforms, centroids) >= cfg.deskew.min_speed * dt)
    if len(moving) == 0:
        return 0
    clouds = [(src_stats.points(src, s), dst_stats.points(dst, d)) for s, d in pairs[moving]]
    times = [(src_stats.points(time_src, s), dst_stats.points(time_dst, d)) for s, d in pairs[moving]]
    current = transforms[moving].copy()
    velocity = np.zeros((len(moving), 3))
    for _ in range(cfg.deskew.iters):
        deskewed = []
        for k, m in enumerate(moving):
            (a, b), (ta, tb) = clouds[k], times[k]
            # current maps the clusters de-skewed with ``velocity`` (none at first): its displacement is the
            # apparent one minus velocity * lag, so the velocity that explains it is (see the module docstring)
            lag = float(tb.mean() - ta.mean())
            shift = current[k, :3, :3] @ centroids[m] + current[k, :3, 3] - centroids[m]
            velocity[k] = (shift + velocity[k] * lag) / max(dt + lag, 0.25 * dt)
            current[k, :3, 3] += velocity[k] * dt - shift  # start from the displacement that velocity implies
            deskewed.append((a - ta[:, None] * velocity[k], b - tb[:, None] * velocity[k]))
            centroids[m] = deskewed[-1][0].mean(axis=0)
        result = registration.register_plane(deskewed, current, cfg.icp, cfg.seed)
        current = result.transforms
    ok = checks.passes(
        current,
        result.mean_error,
        result.iou_ratio,
        np.full(len(moving), window),
        cfg.checks,
        src_centroids=centroids[moving],
    )
    keep = moving[ok]
    matches["transforms"][keep] = current[ok]
    matches["errors"][keep] = result.mean_error[ok]
    matches["iou_ratios"][keep] = result.iou_ratio[ok]
    matches["match_confidence"][keep] = match_confidence(
        result.mean_error[ok], result.iou_ratio[ok], cfg.flow, cfg.checks.max_error
    )
    return int(len(keep))


def _displacement(transforms: np.ndarray, centroids: np.ndarray) -> np.ndarray:
    """(M,) metres each transform moves its source centroid."""
    moved = np.einsum("mij,mj->mi", transforms[:, :3, :3], centroids) + transforms[:, :3, 3]
    return np.linalg.norm(moved - centroids, axis=1)
