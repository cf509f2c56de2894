"""Step 6: rigid registration of cluster pairs, batched, and the match quality used by the checks.

For each pair (src, dst) and an initial src -> dst transform, the SMALLER cluster is registered to the larger one
and the result is inverted when the roles were swapped (as the reference does), by point-to-point ICP
(``icpflow.teacher.registration.icp``), keeping the initial transform when ICP did not lower the mean nearest-neighbour
distance of the moving cluster.

Quality of the final transform (nearest neighbours are exact, not truncated; ``icpflow.scans.neighbours``):

* ``mean_error``: mean nearest-neighbour distance, computed src -> dst and dst -> src, the smaller of the two (the
  reference's ``min`` over both directions);
* ``iou_ratio``: per direction ``inliers / (|src| + |dst| - inliers)`` with inliers the points whose nearest
  neighbour is closer than ``inlier_dist`` (0.1 m), the smaller of the two directions. The reference mixes the
  directions (source inliers over a union built from destination inliers); this keeps the stated formula.

Two backends give the same transforms: ``cpu`` (``registration_cpu``: numba, parallel over pairs, nearest
neighbours from a sorted voxel grid per cluster) and ``torch`` (``registration_torch``: padded batch,
``torch.cdist``; meant for GPUs, runs on CPU).

:func:`plane_errors` measures how well a transform lays a cluster onto its partner's local planes, against the
identity: the static test of ``pipeline._prefer_static``.

:func:`register_plane` is the point-to-plane variant used by the de-skew refinement (``teacher.deskew``) on the
few moving matches, CPU only: src -> dst from the given transform (``icp.icp_point_to_plane``). Quality (error,
IoU ratio) is measured as above, without the keep-the-initial rule.

All points share one frame; clusters (N, 3); transforms (4, 4) float64, src -> dst.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from icpflow.core.geometry import invert, transform_points
from icpflow.scans.normals import plane_normals
from icpflow.teacher.config import ICPConfig
from icpflow.teacher.histogram import subsample
from icpflow.teacher.registration.cpu import register_batch_cpu
from icpflow.teacher.registration.icp import PLANE_NEIGHBOURS, normals
from icpflow.teacher.registration.torch_batch import register_batch_torch


@dataclass
class RegistrationResult:
    """Per-pair ICP output: ``transforms`` (P, 4, 4) float64 src -> dst, ``mean_error`` (P,) metres,
    ``iou_ratio`` (P,) in [0, 1], ``iterations`` (P,) ICP iterations run; ``symmetric_error`` (P,) the mean of
    the two directed mean distances (``mean_error`` is the smaller one); ``identity_error``/``identity_iou``/
    ``identity_symmetric_error`` (P,) the same at the identity (no motion) when asked for
    (``register_clusters(identity=True)``), else None."""

    transforms: np.ndarray
    mean_error: np.ndarray
    iou_ratio: np.ndarray
    iterations: np.ndarray
    symmetric_error: np.ndarray | None = None
    identity_error: np.ndarray | None = None
    identity_iou: np.ndarray | None = None
    identity_symmetric_error: np.ndarray | None = None


def register_plane(
    pairs: list[tuple[np.ndarray, np.ndarray]], inits: np.ndarray, params: ICPConfig, seed: int = 0
) -> RegistrationResult:
    """Point-to-plane registration of P pairs (src (Ns, 3), dst (Nd, 3)) from ``inits`` (P, 4, 4), src -> dst
    (see the module docstring); clusters capped at ``params.max_points`` by a subsample seeded with ``seed``."""
    inits = np.asarray(inits, dtype=np.float64).reshape(-1, 4, 4)
    if len(inits) != len(pairs):
        raise ValueError(f"register_plane: {len(pairs)} pairs but {len(inits)} initial transforms")
    if not pairs:
        return RegistrationResult(
            np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0)
        )
    movings = [subsample(np.asarray(a, np.float64).reshape(-1, 3), int(params.max_points), seed) for a, _ in pairs]
    fixeds = [subsample(np.asarray(b, np.float64).reshape(-1, 3), int(params.max_points), seed) for _, b in pairs]
    out = register_batch_cpu(movings, fixeds, inits, params, [normals(b) for b in fixeds])
    return RegistrationResult(*out[:4], symmetric_error=out[6])


def plane_errors(
    pairs: list[tuple[np.ndarray, np.ndarray]], transforms: np.ndarray, max_points: int, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Mean point-to-plane distances (m) of each src (Ns, 3) onto the local planes of its dst (Nd, 3), at the
    identity and at ``transforms`` (P, 4, 4) src -> dst: two (P,) arrays (infinite for an empty cluster). Each point
    takes its nearest dst point's plane (``icp.normals``); clusters capped at ``max_points`` by a seeded subsample."""
    from scipy.spatial import cKDTree

    transforms = np.asarray(transforms, dtype=np.float64).reshape(-1, 4, 4)
    still, moved = np.full(len(pairs), np.inf), np.full(len(pairs), np.inf)
    for p, (src, dst) in enumerate(pairs):
        src = subsample(np.asarray(src, np.float64).reshape(-1, 3), int(max_points), seed)
        dst = subsample(np.asarray(dst, np.float64).reshape(-1, 3), int(max_points), seed)
        if len(src) == 0 or len(dst) == 0:
            continue
        tree = cKDTree(dst)
        planes = plane_normals(dst, tree.query(dst, min(PLANE_NEIGHBOURS, len(dst)))[1]) if len(dst) >= 3 else None
        if planes is None:
            planes = np.tile([0.0, 0.0, 1.0], (len(dst), 1))
        for out, points in ((still, src), (moved, transform_points(transforms[p], src))):
            _, nearest = tree.query(points)
            out[p] = np.abs(np.einsum("ij,ij->i", points - dst[nearest], planes[nearest])).mean()
    return still, moved


def register_clusters(
    pairs: list[tuple[np.ndarray, np.ndarray]],
    inits: np.ndarray,
    params: ICPConfig,
    seed: int = 0,
    identity: bool = False,
) -> RegistrationResult:
    """Register P cluster pairs (src (Ns, 3), dst (Nd, 3)) from initial src -> dst transforms ``inits`` (P, 4, 4)
    with ``params.backend``.

    Each cluster is capped at ``params.max_points`` by a subsample seeded with ``seed``. A pair with an empty
    cluster keeps its initial transform, with an infinite error and a zero IoU ratio. With ``identity`` the result
    also holds each pair's quality at the identity (the CPU kernel measures it in the same pass; the torch backend
    by a CPU pass with ``max_iter=0``).
    """
    inits = np.asarray(inits, dtype=np.float64).reshape(-1, 4, 4)
    if len(inits) != len(pairs):
        raise ValueError(f"register_clusters: {len(pairs)} pairs but {len(inits)} initial transforms")
    n_pairs = len(pairs)
    if n_pairs == 0:
        return RegistrationResult(
            np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros(0)
        )
    movings, fixeds, starts = [], [], np.empty_like(inits)
    swapped = np.zeros(n_pairs, dtype=bool)
    for p, (src, dst) in enumerate(pairs):
        src = subsample(np.asarray(src, np.float64).reshape(-1, 3), int(params.max_points), seed)
        dst = subsample(np.asarray(dst, np.float64).reshape(-1, 3), int(params.max_points), seed)
        swapped[p] = len(src) > len(dst)  # register the smaller cluster to the larger one
        movings.append(dst if swapped[p] else src)
        fixeds.append(src if swapped[p] else dst)
        starts[p] = invert(inits[p]) if swapped[p] else inits[p]
    identity_error = identity_iou = identity_symmetric = None
    if params.backend == "cpu":
        transforms, errors, ious, iters, still_error, still_iou, symmetric, still_symmetric = register_batch_cpu(
            movings, fixeds, starts, params, identity=identity
        )
    else:
        transforms, errors, ious, iters, symmetric = register_batch_torch(movings, fixeds, starts, params)
        if identity:
            # the identity's quality is measured before ICP starts: no iteration needed
            measure = dataclasses.replace(params, max_iter=0)
            _, _, _, _, still_error, still_iou, _, still_symmetric = register_batch_cpu(
                movings, fixeds, np.tile(np.eye(4), (n_pairs, 1, 1)), measure, identity=True
            )
    if identity:
        identity_error, identity_iou, identity_symmetric = still_error, still_iou, still_symmetric
    for p in np.flatnonzero(swapped):
        transforms[p] = invert(transforms[p])
    return RegistrationResult(
        transforms, errors, ious, iters, symmetric, identity_error, identity_iou, identity_symmetric
    )
