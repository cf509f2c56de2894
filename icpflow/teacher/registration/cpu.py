"""Step 6's batch registration on the CPU (numba, parallel over pairs): register each packed pair with
``icpflow.teacher.registration.icp`` and measure its match quality (see ``icpflow.teacher.registration``).

Nearest neighbours are exact, from one sorted voxel grid per fixed cluster (``icpflow.scans.neighbours``; cells of
:func:`grid_cell`, 0.3 m at the teacher's truncation) that serves both the ICP correspondences and the quality.
"""

from __future__ import annotations

import numba
import numpy as np

from icpflow.scans.neighbours import build_grid, nn_stats, transform_cloud
from icpflow.teacher.config import ICPConfig
from icpflow.teacher.histogram import pack
from icpflow.teacher.registration.icp import PLANE_MAX_ITER, icp_point_to_plane, icp_point_to_point

# Cell size (metres) of the grid answering the exact nearest-neighbour queries. Any size gives the same
# neighbours; on the AV2 pair's largest cluster 0.3 m cells answer the ICP's 0.1 m-truncated queries 1.7x faster
# than 0.1 m cells, and one grid then serves the ICP and the quality's untruncated queries (docs/history.md, "real
# time on a laptop CPU": the teacher's profile of its ICP step).
_GRID_CELL = 0.3


def grid_cell(max_corr: float) -> float:
    """Cells (m) of the neighbour grid for ICP truncated at ``max_corr``: ``_GRID_CELL``, or ``max_corr / 4`` for
    a truncation beyond four times it (the refinement's coarse-to-fine ICP, ``fastflow3d.inference.refine``: 0.5 m
    cells at 2 m). A converging ICP's queries lie near their neighbours, and smaller cells scan fewer points for them;
    a query with nothing within reach scans the component's points (``neighbours.nearest``). On each stream's
    captured pairs the refinement is quicker with ``max_corr / 4`` than with ``max_corr / 2`` (1 m cells at 2 m) or
    0.3 m cells at every stage, with the same outputs (BENCHMARKS.md, "Refinement"). The neighbours are the same at
    any cell size; the teacher's 0.1 m truncation keeps 0.3 m cells."""
    return max(_GRID_CELL, float(max_corr) / 4)


@numba.njit(cache=True, nogil=True)
def _quality_from(moved, err_fwd, inl_fwd, fixed, cell, inlier_d2):
    """(mean error, IoU ratio, symmetric error) of moved (M, 3) on fixed (N, 3) (module docstring), given the
    forward direction's mean distance and inlier count: the backward one is measured here."""
    err_bwd, inl_bwd = nn_stats(fixed, moved, build_grid(moved, cell), cell, inlier_d2)
    n_all = moved.shape[0] + fixed.shape[0]
    iou = min(inl_fwd / (n_all - inl_fwd), inl_bwd / (n_all - inl_bwd))
    return min(err_fwd, err_bwd), iou, 0.5 * (err_fwd + err_bwd)


@numba.njit(cache=True, nogil=True)
def _quality(moved, fixed, fixed_grid, cell, inlier_d2):
    """:func:`_quality_from` with the forward direction measured too (``fixed_grid``: fixed's ``build_grid``)."""
    err_fwd, inl_fwd = nn_stats(moved, fixed, fixed_grid, cell, inlier_d2)
    return _quality_from(moved, err_fwd, inl_fwd, fixed, cell, inlier_d2)


@numba.njit(cache=True, nogil=True)
def _register_one(
    moving, fixed, fixed_normals, init, max_corr, max_iter, rel_rmse, yaw_only, plane, inlier_d2, grid_cell, identity
):
    """Register moving (M, 3) onto fixed (N, 3) from ``init``, point-to-point (keeping ``init`` when ICP did not
    lower the forward mean distance) or, with ``plane``, point-to-plane along ``fixed_normals`` (N, 3); returns
    (transform, mean error, IoU ratio, iterations, mean error at the identity, IoU ratio at the identity,
    symmetric error, symmetric error at the identity), error and IoU ratio as in the module docstring (the smaller
    of the two directions each), the symmetric error the mean of the two directed mean distances; the identity's
    only with ``identity`` (else inf and 0)."""
    fixed_grid = build_grid(fixed, grid_cell)
    err_id, iou_id, sym_id = np.inf, 0.0, np.inf
    if identity:  # the same quality at no motion (what a separate registration with max_iter=0 measures)
        err_id, iou_id, sym_id = _quality(moving, fixed, fixed_grid, grid_cell, inlier_d2)
    if plane:
        transform, n_iter = icp_point_to_plane(
            moving, fixed, fixed_normals, fixed_grid, grid_cell, init, max_corr, PLANE_MAX_ITER
        )
    else:
        transform, n_iter = icp_point_to_point(
            moving, fixed, fixed_grid, grid_cell, init, max_corr, max_iter, rel_rmse, yaw_only
        )
    moved = transform_cloud(moving, transform)
    err_fwd, inl_fwd = nn_stats(moved, fixed, fixed_grid, grid_cell, inlier_d2)
    if not plane and n_iter > 0:
        moved_init = transform_cloud(moving, init)
        err_init, inl_init = nn_stats(moved_init, fixed, fixed_grid, grid_cell, inlier_d2)
        if not err_fwd < err_init:  # ICP made it worse: keep the initial transform
            transform, moved, err_fwd, inl_fwd = init, moved_init, err_init, inl_init
    error, iou, symmetric = _quality_from(moved, err_fwd, inl_fwd, fixed, grid_cell, inlier_d2)
    return transform, error, iou, n_iter, err_id, iou_id, symmetric, sym_id


@numba.njit(cache=True, nogil=True, parallel=True)
def _register_batch(
    mov_all,
    mov_off,
    fix_all,
    fix_off,
    nrm_all,
    inits,
    max_corr,
    max_iter,
    rel_rmse,
    yaw_only,
    plane,
    inlier_dist,
    grid_cell,
    n_workers,
    identity,
):
    """:func:`_register_one` for P packed pairs (``nrm_all`` packed like ``fix_all`` with ``plane``, else unused);
    returns (transforms, errors, IoU ratios, iterations, errors at the identity, IoU ratios at the identity,
    symmetric errors, symmetric errors at the identity).
    Worker w takes pairs w, w + n_workers, ...: with the pairs sorted by decreasing size this balances the load,
    which numba's contiguous split of a prange does not."""
    n_pairs = inits.shape[0]
    transforms = np.zeros((n_pairs, 4, 4))
    errors = np.full(n_pairs, np.inf)
    ious = np.zeros(n_pairs)
    iters = np.zeros(n_pairs, dtype=np.int64)
    errors_id = np.full(n_pairs, np.inf)
    ious_id = np.zeros(n_pairs)
    syms = np.full(n_pairs, np.inf)
    syms_id = np.full(n_pairs, np.inf)
    inlier_d2 = inlier_dist * inlier_dist
    for w in numba.prange(n_workers):
        for p in range(w, n_pairs, n_workers):
            moving = mov_all[mov_off[p] : mov_off[p + 1]]
            fixed = fix_all[fix_off[p] : fix_off[p + 1]]
            fixed_normals = nrm_all[fix_off[p] : fix_off[p + 1]] if plane else nrm_all
            transforms[p] = inits[p]
            if moving.shape[0] > 0 and fixed.shape[0] > 0:
                (
                    transforms[p],
                    errors[p],
                    ious[p],
                    iters[p],
                    errors_id[p],
                    ious_id[p],
                    syms[p],
                    syms_id[p],
                ) = _register_one(
                    moving,
                    fixed,
                    fixed_normals,
                    inits[p].copy(),
                    max_corr,
                    max_iter,
                    rel_rmse,
                    yaw_only,
                    plane,
                    inlier_d2,
                    grid_cell,
                    identity,
                )
    return transforms, errors, ious, iters, errors_id, ious_id, syms, syms_id


def register_batch_cpu(
    movings, fixeds, starts, params: ICPConfig, fixed_normals=None, identity: bool = False
) -> tuple[np.ndarray, ...]:
    """:func:`_register_batch` on lists of clouds (point-to-plane when the fixed clouds' normals are given):
    (transforms, errors, ious, iterations, errors at the identity, IoU ratios at the identity, symmetric errors,
    symmetric errors at the identity) in the input order (the identity's measured only with ``identity``, else inf
    and 0)."""
    order = np.argsort([-(len(m) + len(f)) for m, f in zip(movings, fixeds)], kind="stable")
    mov_all, mov_off = pack([movings[k] for k in order])
    fix_all, fix_off = pack([fixeds[k] for k in order])
    plane = fixed_normals is not None
    nrm_all = pack([fixed_normals[k] for k in order])[0] if plane else np.zeros((0, 3))
    out = _register_batch(
        mov_all,
        mov_off,
        fix_all,
        fix_off,
        nrm_all,
        starts[order],
        float(params.max_corr),
        int(params.max_iter),
        float(params.rel_rmse),
        params.dof == "yaw",
        plane,
        float(params.max_corr),  # the IoU inlier distance is the correspondence truncation
        grid_cell(params.max_corr),
        numba.get_num_threads(),
        identity,
    )
    result = tuple(np.empty_like(a) for a in out)
    for a, b in zip(result, out):
        a[order] = b
    return result


@numba.njit(cache=True, nogil=True, parallel=True)
def _register_stages_batch(
    mov_all,
    mov_off,
    fix_all,
    fix_off,
    given_all,
    inits,
    max_corrs,
    cells,
    max_iter,
    rel_rmse,
    yaw_only,
    identities,
    n_workers,
):
    """Coarse-to-fine point-to-point ICP of P packed pairs (see :func:`register_stages_cpu`); returns (transforms,
    errors, IoU ratios, errors at the identity, IoU ratios at the identity, errors of the given clouds, IoU ratios
    of the given clouds), the identity's measured only where ``identities`` (P,) bool (else inf and 0). Worker w
    takes pairs w, w + n_workers, ... (pairs sorted by decreasing size). A transform's
    forward mean distance is measured once and carried to the next stage and the quality: the student's refinement
    makes 5 passes over the moving cloud rather than 8 (BENCHMARKS.md, "Refinement")."""
    n_pairs = inits.shape[0]
    transforms = np.zeros((n_pairs, 4, 4))
    out = np.full((6, n_pairs), np.inf)
    out[1], out[3], out[5] = 0.0, 0.0, 0.0
    last = max_corrs.shape[0] - 1
    inlier_d2 = max_corrs[last] * max_corrs[last]
    for w in numba.prange(n_workers):
        for p in range(w, n_pairs, n_workers):
            moving = mov_all[mov_off[p] : mov_off[p + 1]]
            fixed = fix_all[fix_off[p] : fix_off[p + 1]]
            transform = inits[p].copy()
            if moving.shape[0] == 0 or fixed.shape[0] == 0:
                transforms[p] = transform
                continue
            grid = build_grid(fixed, cells[0])
            # the forward (mean distance, inliers at the last truncation) of the current transform, measured once
            # each: exact, whatever the grid's cell, so a stage's start is its last stage's result (-1: not yet)
            current, current_inliers = -1.0, 0
            for s in range(max_corrs.shape[0]):
                if s > 0 and cells[s] != cells[s - 1]:
                    grid = build_grid(fixed, cells[s])
                init = transform
                transform, n_iter = icp_point_to_point(
                    moving, fixed, grid, cells[s], init, max_corrs[s], max_iter, rel_rmse, yaw_only
                )
                if n_iter > 0:  # ICP made the forward mean distance no smaller: keep the stage's start
                    if current < 0:
                        current, current_inliers = nn_stats(
                            transform_cloud(moving, init), fixed, grid, cells[s], inlier_d2
                        )
                    moved, moved_inliers = nn_stats(
                        transform_cloud(moving, transform), fixed, grid, cells[s], inlier_d2
                    )
                    if moved < current:
                        current, current_inliers = moved, moved_inliers
                    else:
                        transform = init
            transforms[p] = transform
            given = given_all[mov_off[p] : mov_off[p + 1]]
            moved_cloud = transform_cloud(moving, transform)
            if current < 0:
                current, current_inliers = nn_stats(moved_cloud, fixed, grid, cells[last], inlier_d2)
            out[0, p], out[1, p], _ = _quality_from(
                moved_cloud, current, current_inliers, fixed, cells[last], inlier_d2
            )
            if identities[p]:
                out[2, p], out[3, p], _ = _quality(moving, fixed, grid, cells[last], inlier_d2)
            out[4, p], out[5, p], _ = _quality(given, fixed, grid, cells[last], inlier_d2)
    return transforms, out[0], out[1], out[2], out[3], out[4], out[5]


def register_stages_cpu(
    movings, fixeds, givens, starts, max_corrs, max_iter: int, rel_rmse: float, yaw_only: bool, identities=None
) -> tuple[np.ndarray, ...]:
    """Coarse-to-fine point-to-point ICP of each moving cloud (M_p, 3) onto its fixed cloud (N_p, 3) from its
    start (P, 4, 4): one stage per truncation of ``max_corrs`` (metres, coarse to fine), each from the last one's
    transform, all in one compiled call. The same transforms as :func:`register_batch_cpu` run stage by stage, and
    the same quality at the last stage's truncation (mean error and IoU ratio, as :func:`_register_one`) of three
    clouds per pair: the registered one, the identity's (the moving cloud as it is) and ``givens`` (M_p, 3), the
    moving points placed by some other motion (a per-point flow). Returns (transforms, errors, IoU ratios, errors
    at the identity, IoU ratios at the identity, errors of the givens, IoU ratios of the givens), in input order.
    ``identities`` (P,) bool: the pairs whose quality at the identity is wanted (None: all; the others get inf and
    0: an unbounded nearest-neighbour pass each way, a tenth of the refinement's registration on KITTI's pairs for
    the components it cannot keep static)."""
    order = np.argsort([-(len(m) + len(f)) for m, f in zip(movings, fixeds)], kind="stable")
    mov_all, mov_off = pack([movings[k] for k in order])
    fix_all, fix_off = pack([fixeds[k] for k in order])
    given_all, _ = pack([givens[k] for k in order])
    max_corrs = np.asarray(max_corrs, np.float64)
    cells = np.array([grid_cell(d) for d in max_corrs])
    out = _register_stages_batch(
        mov_all,
        mov_off,
        fix_all,
        fix_off,
        given_all,
        np.asarray(starts, np.float64)[order],
        max_corrs,
        cells,
        int(max_iter),
        float(rel_rmse),
        bool(yaw_only),
        np.ones(len(order), bool) if identities is None else np.asarray(identities, bool)[order],
        numba.get_num_threads(),
    )
    result = tuple(np.empty_like(a) for a in out)
    for a, b in zip(result, out):
        a[order] = b
    return result
