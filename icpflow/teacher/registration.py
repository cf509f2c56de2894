"""Step 6: rigid registration of cluster pairs (point-to-point ICP) and the match quality used by the checks.

For each pair (src, dst) and an initial src -> dst transform, the SMALLER cluster is registered to the larger one
and the result is inverted when the roles were swapped (as the reference does). ICP:

* correspondences: each moving point's nearest fixed point, kept when closer than ``max_corr`` (0.1 m);
* update: the closed-form (Kabsch) rigid transform from the moving points to their correspondences; with
  ``icp_dof="yaw"`` the rotation is about z only (angle ``atan2(H01 - H10, H00 + H11)`` of the centred
  cross-covariance H), the translation stays 3D;
* stop after ``max_iter`` (100) iterations, when the RMSE of an iteration's correspondences after its update fell
  by at most ``rel_rmse`` (1e-6) relative to the previous iteration's (rising counts as converged; pytorch3d's ICP,
  which the reference uses, stops the same way), or with fewer than 3 correspondences;
* keep the initial transform when ICP did not lower the mean nearest-neighbour distance of the moving cluster.

Quality of the final transform (nearest neighbours are exact, not truncated):

* ``mean_error``: mean nearest-neighbour distance, computed src -> dst and dst -> src, the smaller of the two (the
  reference's ``min`` over both directions);
* ``iou_ratio``: per direction ``inliers / (|src| + |dst| - inliers)`` with inliers the points whose nearest
  neighbour is closer than ``inlier_dist`` (0.1 m), the smaller of the two directions. The reference mixes the
  directions (source inliers over a union built from destination inliers); this keeps the stated formula.

Two backends give the same transforms: ``cpu`` (numba, parallel over pairs, nearest neighbours from a sorted
voxel grid per cluster) and ``torch`` (padded batch, ``torch.cdist``; meant for GPUs, runs on CPU).

:func:`register_plane` is the point-to-plane variant used by the de-skew refinement (``teacher.deskew``) on the
few moving matches, CPU only (numba): src -> dst from the given transform, each moved source point paired with
its nearest destination point within ``max_corr``; the residual is the distance along that destination point's
normal (smallest principal axis of its ``PLANE_NEIGHBOURS`` nearest neighbours); each iteration solves the
linearised least-squares update of a rotation about z (through the moved source centroid) and a 3D translation,
which does not slide along flat sides the way point-to-point ICP does between differently sampled scans; it stops
after 30 iterations, when the update is below 1e-4 (rad and m), or with fewer than 4 correspondences.
Quality (error, IoU ratio) is measured as above, without the keep-the-initial rule.

All points share one frame; clusters (N, 3); transforms (4, 4) float64, src -> dst.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from icpflow.geometry import invert
from icpflow.teacher.histogram import pack, subsample

# Cell size (metres) of the grid answering exact nearest-neighbour queries in the quality evaluation.
_EVAL_CELL = 0.3
# Grid shells searched before a nearest-neighbour query falls back to scanning every point.
_MAX_SHELL = 3
# Squared distances at or above this are "nothing found yet" (no z-range pruning).
_FAR = 1e30
# Neighbours (the point included) whose covariance gives a destination point's normal in ``register_plane``.
PLANE_NEIGHBOURS = 10
# ``register_plane`` stops when an update turns by less than this (rad) and moves by less than this (m), or after
# ``_PLANE_MAX_ITER`` iterations (nearest-neighbour switches can make it cycle at the 0.1 mm level).
_PLANE_TOL = 1e-4
_PLANE_MAX_ITER = 30


@dataclass(frozen=True)
class ICPParams:
    """ICP settings, read from ``ICPFlowConfig`` by :func:`params_from_config`."""

    max_corr: float = 0.1
    max_iter: int = 100
    rel_rmse: float = 1e-6
    inlier_dist: float = 0.1
    max_points: int = 10000
    seed: int = 0
    yaw_only: bool = False  # ``icp_dof="yaw"``: rotation about z only (road objects do not roll or pitch)


def params_from_config(cfg) -> ICPParams:
    """The ICP fields of an ``ICPFlowConfig``."""
    return ICPParams(
        max_corr=float(cfg.icp_max_corr),
        max_iter=int(cfg.icp_max_iter),
        rel_rmse=float(cfg.icp_rel_rmse),
        inlier_dist=float(cfg.icp_max_corr),
        max_points=int(cfg.max_points),
        seed=int(cfg.seed),
        yaw_only=cfg.icp_dof == "yaw",
    )


@dataclass
class RegistrationResult:
    """Per-pair ICP output: ``transforms`` (P, 4, 4) float64 src -> dst, ``mean_error`` (P,) metres,
    ``iou_ratio`` (P,) in [0, 1], ``iterations`` (P,) ICP iterations run."""

    transforms: np.ndarray
    mean_error: np.ndarray
    iou_ratio: np.ndarray
    iterations: np.ndarray


# ----------------------------------------------------------------------------------------------- cpu backend


@numba.njit(cache=True)
def _grid(points, cell):
    """Voxel grid of (N, 3) points, sorted by xy column then z cell: (origin (3,), dims (3,), column starts
    (nx * ny + 1,), z cell of each sorted point (N,), sorted point order (N,))."""
    origin = np.empty(3)
    dims = np.empty(3, dtype=np.int64)
    for a in range(3):
        lo, hi = points[:, a].min(), points[:, a].max()
        origin[a] = lo
        dims[a] = int((hi - lo) / cell) + 1
    n = points.shape[0]
    columns = np.empty(n, dtype=np.int64)
    z_cells = np.empty(n, dtype=np.int64)
    for i in range(n):
        cx = min(int((points[i, 0] - origin[0]) / cell), dims[0] - 1)
        cy = min(int((points[i, 1] - origin[1]) / cell), dims[1] - 1)
        z_cells[i] = min(int((points[i, 2] - origin[2]) / cell), dims[2] - 1)
        columns[i] = cx * dims[1] + cy
    order = np.argsort(columns * dims[2] + z_cells, kind="mergesort")
    starts = np.zeros(dims[0] * dims[1] + 1, dtype=np.int64)
    for i in range(n):
        starts[columns[i] + 1] += 1
    for k in range(1, starts.shape[0]):
        starts[k] += starts[k - 1]
    return origin, dims, starts, z_cells[order], order


@numba.njit(cache=True)
def _scan_column(q, points, starts, z_sorted, order, dims, cx, cy, z0, z1, best_d2, best_j):
    """Closest point to q among grid column (cx, cy), z cells z0..z1 (already clipped)."""
    column = cx * dims[1] + cy
    lo, hi = starts[column], starts[column + 1]
    while lo < hi:  # binary search for the column's first point at z cell >= z0 (tall columns hold many points)
        mid = (lo + hi) // 2
        if z_sorted[mid] < z0:
            lo = mid + 1
        else:
            hi = mid
    for s in range(lo, starts[column + 1]):
        if z_sorted[s] > z1:
            break
        j = order[s]
        d2 = (points[j, 0] - q[0]) ** 2 + (points[j, 1] - q[1]) ** 2 + (points[j, 2] - q[2]) ** 2
        if d2 < best_d2:
            best_d2, best_j = d2, j
    return best_d2, best_j


@numba.njit(cache=True)
def _nearest_brute(q, points, max_d2):
    """Nearest of ``points`` to q by a full scan: (index, squared distance), or (-1, max_d2)."""
    best_d2, best_j = max_d2, -1
    for j in range(points.shape[0]):
        d2 = (points[j, 0] - q[0]) ** 2 + (points[j, 1] - q[1]) ** 2 + (points[j, 2] - q[2]) ** 2
        if d2 < best_d2:
            best_d2, best_j = d2, j
    return best_j, best_d2


@numba.njit(cache=True)
def _nearest(q, points, grid, cell, max_d2):
    """Nearest of ``points`` to q: (index, squared distance), or (-1, max_d2) if none is closer than sqrt(max_d2).

    Visits cubic shells of grid cells around q's cell, nearest shell first, and stops as soon as every unvisited
    cell is farther than the best point found (exact), or than sqrt(max_d2). A query that would need shells
    beyond ``_MAX_SHELL`` (far from the grid or in a large empty part of it) scans all points instead.
    """
    origin, dims, starts, z_sorted, order = grid
    c0 = int(np.floor((q[0] - origin[0]) / cell))
    c1 = int(np.floor((q[1] - origin[1]) / cell))
    c2 = int(np.floor((q[2] - origin[2]) / cell))
    # Chebyshev distance in cells from q's cell to the grid box
    gap = max(0, -c0, c0 - (dims[0] - 1), -c1, c1 - (dims[1] - 1), -c2, c2 - (dims[2] - 1))
    if gap > 1 and ((gap - 1) * cell) ** 2 >= max_d2:
        return -1, max_d2  # the whole grid is out of reach
    best_d2, best_j = max_d2, -1
    r = gap
    r_max = gap + max(dims[0], dims[1], dims[2])
    while r <= r_max:
        if r > 1 and ((r - 1) * cell) ** 2 >= best_d2:
            break  # every point in shell r or beyond is at least (r - 1) cells away
        if r > _MAX_SHELL:
            return _nearest_brute(q, points, max_d2)
        z_lo, z_hi = max(c2 - r, 0), min(c2 + r, dims[2] - 1)
        for cx in range(max(c0 - r, 0), min(c0 + r, dims[0] - 1) + 1):
            gx = max(0.0, origin[0] + cx * cell - q[0], q[0] - origin[0] - (cx + 1) * cell)
            if gx * gx >= best_d2:
                continue  # the whole slab of columns is farther than the best point so far
            for cy in range(max(c1 - r, 0), min(c1 + r, dims[1] - 1) + 1):
                gy = max(0.0, origin[1] + cy * cell - q[1], q[1] - origin[1] - (cy + 1) * cell)
                gxy2 = gx * gx + gy * gy
                if gxy2 >= best_d2:
                    continue
                z_from, z_to = z_lo, z_hi
                if best_d2 < _FAR:  # only z cells that can still hold a closer point
                    reach = np.sqrt(best_d2 - gxy2)
                    z_from = max(z_lo, int(np.floor((q[2] - reach - origin[2]) / cell)))
                    z_to = min(z_hi, int(np.floor((q[2] + reach - origin[2]) / cell)))
                if abs(cx - c0) == r or abs(cy - c1) == r:
                    if z_from <= z_to:
                        best_d2, best_j = _scan_column(q, points, starts, z_sorted, order, dims, cx, cy, z_from, z_to, best_d2, best_j)
                else:  # inside the shell's xy square: only its bottom and top cells belong to shell r
                    if z_from <= c2 - r <= z_to:
                        best_d2, best_j = _scan_column(q, points, starts, z_sorted, order, dims, cx, cy, c2 - r, c2 - r, best_d2, best_j)
                    if z_from <= c2 + r <= z_to:
                        best_d2, best_j = _scan_column(q, points, starts, z_sorted, order, dims, cx, cy, c2 + r, c2 + r, best_d2, best_j)
        r += 1
    return best_j, best_d2


@numba.njit(cache=True)
def _transform(points, transform):
    """(N, 3) points mapped by a (4, 4) transform."""
    out = np.empty_like(points)
    for i in range(points.shape[0]):
        for a in range(3):
            out[i, a] = (
                transform[a, 0] * points[i, 0] + transform[a, 1] * points[i, 1] + transform[a, 2] * points[i, 2]
                + transform[a, 3]
            )
    return out


@numba.njit(cache=True)
def _nn_stats(query, points, grid, cell, inlier_d2):
    """Exact nearest-neighbour distances from query (M, 3) to points (N, 3) with their ``_grid``:
    (mean distance, inlier count)."""
    total = 0.0
    inliers = 0
    for i in range(query.shape[0]):
        _, d2 = _nearest(query[i], points, grid, cell, np.inf)
        total += np.sqrt(d2)
        if d2 < inlier_d2:
            inliers += 1
    return total / query.shape[0], inliers


@numba.njit(cache=True)
def _icp(moving, fixed, init, max_corr, max_iter, rel_rmse, yaw_only):
    """Point-to-point ICP of moving (M, 3) onto fixed (N, 3) from ``init``: ((4, 4) transform, iterations run)."""
    grid = _grid(fixed, max_corr)
    transform = init.copy()
    max_d2 = max_corr * max_corr
    matches = np.empty(moving.shape[0], dtype=np.int64)
    prev_rmse = -1.0  # negative: no previous iteration
    iterations = 0
    q = np.empty(3)
    while iterations < max_iter:
        sum_m = np.zeros(3)
        sum_f = np.zeros(3)
        cross = np.zeros((3, 3))
        count = 0
        for i in range(moving.shape[0]):
            for a in range(3):
                q[a] = (
                    transform[a, 0] * moving[i, 0] + transform[a, 1] * moving[i, 1] + transform[a, 2] * moving[i, 2]
                    + transform[a, 3]
                )
            j, _ = _nearest(q, fixed, grid, max_corr, max_d2)
            matches[i] = j
            if j < 0:
                continue
            count += 1
            for a in range(3):
                sum_m[a] += moving[i, a]
                sum_f[a] += fixed[j, a]
                for b in range(3):
                    cross[a, b] += moving[i, a] * fixed[j, b]
        if count < 3:
            break
        mean_m = sum_m / count
        mean_f = sum_f / count
        h = cross - count * np.outer(mean_m, mean_f)
        if yaw_only:
            angle = np.arctan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
            rotation = np.eye(3)
            rotation[0, 0], rotation[0, 1] = np.cos(angle), -np.sin(angle)
            rotation[1, 0], rotation[1, 1] = np.sin(angle), np.cos(angle)
        else:
            u, _, vt = np.linalg.svd(h)
            d = np.eye(3)
            if np.linalg.det(vt.T @ u.T) < 0.0:  # a reflection: flip the weakest axis
                d[2, 2] = -1.0
            rotation = vt.T @ d @ u.T
        transform = np.eye(4)
        transform[:3, :3] = rotation
        transform[:3, 3] = mean_f - rotation @ mean_m
        iterations += 1
        # RMSE of this iteration's correspondences after the update (as pytorch3d's ICP, used by the reference)
        sse = 0.0
        for i in range(moving.shape[0]):
            j = matches[i]
            if j >= 0:
                for a in range(3):
                    r = (
                        transform[a, 0] * moving[i, 0] + transform[a, 1] * moving[i, 1]
                        + transform[a, 2] * moving[i, 2] + transform[a, 3] - fixed[j, a]
                    )
                    sse += r * r
        rmse = np.sqrt(sse / count)
        if prev_rmse >= 0.0 and prev_rmse - rmse <= rel_rmse * prev_rmse:
            break  # the RMSE stopped falling by more than rel_rmse (relative)
        prev_rmse = rmse
    return transform, iterations


@numba.njit(cache=True)
def _register_one(moving, fixed, fixed_normals, init, max_corr, max_iter, rel_rmse, yaw_only, plane, inlier_d2,
                  eval_cell):
    """Register moving (M, 3) onto fixed (N, 3) from ``init``, point-to-point (keeping ``init`` when ICP did not
    lower the forward mean distance) or, with ``plane``, point-to-plane along ``fixed_normals`` (N, 3); returns
    (transform, mean error, IoU ratio, iterations), error and IoU ratio as in the module docstring (the smaller of
    the two directions each)."""
    fixed_grid = _grid(fixed, eval_cell)
    if plane:
        transform, n_iter = _icp_plane(moving, fixed, fixed_normals, init, max_corr, _PLANE_MAX_ITER)
    else:
        transform, n_iter = _icp(moving, fixed, init, max_corr, max_iter, rel_rmse, yaw_only)
    moved = _transform(moving, transform)
    err_fwd, inl_fwd = _nn_stats(moved, fixed, fixed_grid, eval_cell, inlier_d2)
    if not plane and n_iter > 0:
        moved_init = _transform(moving, init)
        err_init, inl_init = _nn_stats(moved_init, fixed, fixed_grid, eval_cell, inlier_d2)
        if not err_fwd < err_init:  # ICP made it worse: keep the initial transform
            transform, moved, err_fwd, inl_fwd = init, moved_init, err_init, inl_init
    err_bwd, inl_bwd = _nn_stats(fixed, moved, _grid(moved, eval_cell), eval_cell, inlier_d2)
    n_all = moving.shape[0] + fixed.shape[0]
    iou = min(inl_fwd / (n_all - inl_fwd), inl_bwd / (n_all - inl_bwd))
    return transform, min(err_fwd, err_bwd), iou, n_iter


@numba.njit(cache=True, parallel=True)
def _register_batch(mov_all, mov_off, fix_all, fix_off, nrm_all, inits, max_corr, max_iter, rel_rmse, yaw_only,
                    plane, inlier_dist, eval_cell, n_workers):
    """:func:`_register_one` for P packed pairs (``nrm_all`` packed like ``fix_all`` with ``plane``, else unused).
    Worker w takes pairs w, w + n_workers, ...: with the pairs sorted by decreasing size this balances the load,
    which numba's contiguous split of a prange does not."""
    n_pairs = inits.shape[0]
    transforms = np.zeros((n_pairs, 4, 4))
    errors = np.full(n_pairs, np.inf)
    ious = np.zeros(n_pairs)
    iters = np.zeros(n_pairs, dtype=np.int64)
    inlier_d2 = inlier_dist * inlier_dist
    for w in numba.prange(n_workers):
        for p in range(w, n_pairs, n_workers):
            moving = mov_all[mov_off[p] : mov_off[p + 1]]
            fixed = fix_all[fix_off[p] : fix_off[p + 1]]
            fixed_normals = nrm_all[fix_off[p] : fix_off[p + 1]] if plane else nrm_all
            transforms[p] = inits[p]
            if moving.shape[0] > 0 and fixed.shape[0] > 0:
                transforms[p], errors[p], ious[p], iters[p] = _register_one(
                    moving, fixed, fixed_normals, inits[p].copy(), max_corr, max_iter, rel_rmse, yaw_only, plane,
                    inlier_d2, eval_cell,
                )
    return transforms, errors, ious, iters


def _run_batch(movings, fixeds, starts, params: ICPParams, fixed_normals=None) -> tuple[np.ndarray, ...]:
    """:func:`_register_batch` on lists of clouds (point-to-plane when the fixed clouds' normals are given):
    (transforms, errors, ious, iterations) in the input order."""
    order = np.argsort([-(len(m) + len(f)) for m, f in zip(movings, fixeds)], kind="stable")
    mov_all, mov_off = pack([movings[k] for k in order])
    fix_all, fix_off = pack([fixeds[k] for k in order])
    plane = fixed_normals is not None
    nrm_all = pack([fixed_normals[k] for k in order])[0] if plane else np.zeros((0, 3))
    out = _register_batch(
        mov_all, mov_off, fix_all, fix_off, nrm_all, starts[order], params.max_corr, params.max_iter,
        params.rel_rmse, params.yaw_only, plane, params.inlier_dist, _EVAL_CELL,
        numba.get_num_threads(),
    )
    result = tuple(np.empty_like(a) for a in out)
    for a, b in zip(result, out):
        a[order] = b
    return result


@numba.njit(cache=True)
def _icp_plane(moving, fixed, normals, init, max_corr, max_iter):
    """Point-to-plane ICP (rotation about z and 3D translation) of moving (M, 3) onto fixed (N, 3) with unit
    ``normals`` (N, 3), from ``init``: ((4, 4) transform, iterations run)."""
    grid = _grid(fixed, max_corr)
    transform = init.copy()
    max_d2 = max_corr * max_corr
    iterations = 0
    while iterations < max_iter:
        moved = _transform(moving, transform)
        centre = np.zeros(3)
        for i in range(moved.shape[0]):
            centre += moved[i]
        centre /= moved.shape[0]
        ata = np.zeros((4, 4))
        atb = np.zeros(4)
        row = np.empty(4)
        count = 0
        for i in range(moved.shape[0]):
            j, _ = _nearest(moved[i], fixed, grid, max_corr, max_d2)
            if j < 0:
                continue
            n = normals[j]
            residual = (moved[i, 0] - fixed[j, 0]) * n[0] + (moved[i, 1] - fixed[j, 1]) * n[1] + (
                moved[i, 2] - fixed[j, 2]) * n[2]
            # d(residual)/d(yaw) about the centre, then d/d(translation) = the normal
            row[0] = (moved[i, 0] - centre[0]) * n[1] - (moved[i, 1] - centre[1]) * n[0]
            row[1], row[2], row[3] = n[0], n[1], n[2]
            for a in range(4):
                atb[a] -= row[a] * residual
                for b in range(4):
                    ata[a, b] += row[a] * row[b]
            count += 1
        if count < 4:
            break
        damping = 1e-9 * (ata[0, 0] + ata[1, 1] + ata[2, 2] + ata[3, 3]) + 1e-12
        for a in range(4):
            ata[a, a] += damping
        x = np.linalg.solve(ata, atb)
        c, s = np.cos(x[0]), np.sin(x[0])
        step = np.eye(4)
        step[0, 0], step[0, 1], step[1, 0], step[1, 1] = c, -s, s, c
        step[0, 3] = centre[0] - c * centre[0] + s * centre[1] + x[1]
        step[1, 3] = centre[1] - s * centre[0] - c * centre[1] + x[2]
        step[2, 3] = x[3]
        transform = step @ transform
        iterations += 1
        if abs(x[0]) < _PLANE_TOL and abs(x[1]) < _PLANE_TOL and abs(x[2]) < _PLANE_TOL and abs(x[3]) < _PLANE_TOL:
            break
    return transform, iterations


def normals(points: np.ndarray, neighbours: int = PLANE_NEIGHBOURS) -> np.ndarray:
    """(N, 3) float64 unit normals of (N, 3) points: the smallest principal axis of each point's ``neighbours``
    nearest points (itself included; fewer when the cloud is smaller). Sign arbitrary."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, np.float64).reshape(-1, 3)
    k = min(neighbours, len(points))
    if k < 3:
        return np.tile([0.0, 0.0, 1.0], (len(points), 1))
    _, nearest = cKDTree(points).query(points, k)
    local = points[nearest] - points[nearest].mean(axis=1, keepdims=True)
    _, axes = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))
    return axes[:, :, 0]


def register_plane(pairs: list[tuple[np.ndarray, np.ndarray]], inits: np.ndarray, params: ICPParams
                   ) -> RegistrationResult:
    """Point-to-plane registration of P pairs (src (Ns, 3), dst (Nd, 3)) from ``inits`` (P, 4, 4), src -> dst
    (see the module docstring); clusters capped at ``params.max_points`` by a seeded subsample."""
    inits = np.asarray(inits, dtype=np.float64).reshape(-1, 4, 4)
    if len(inits) != len(pairs):
        raise ValueError(f"register_plane: {len(pairs)} pairs but {len(inits)} initial transforms")
    if not pairs:
        return RegistrationResult(np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    movings = [subsample(np.asarray(a, np.float64).reshape(-1, 3), params.max_points, params.seed) for a, _ in pairs]
    fixeds = [subsample(np.asarray(b, np.float64).reshape(-1, 3), params.max_points, params.seed) for _, b in pairs]
    transforms, errors, ious, iters = _run_batch(movings, fixeds, inits, params, [normals(b) for b in fixeds])
    return RegistrationResult(transforms, errors, ious, iters)


# --------------------------------------------------------------------------------------------- torch backend


def _register_torch(movings, fixeds, inits, params: ICPParams, device=None):
    """Padded batched ICP in torch: same algorithm and outputs as the cpu backend (float64 throughout)."""
    import torch

    device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    n_pairs = len(movings)
    m_max = max(1, max(len(m) for m in movings))
    f_max = max(1, max(len(f) for f in fixeds))
    far = 1e6  # padding coordinate: never a neighbour of a real point, never within any threshold
    mov = torch.full((n_pairs, m_max, 3), far, dtype=torch.float64)
    fix = torch.full((n_pairs, f_max, 3), -far, dtype=torch.float64)
    m_mask = torch.zeros((n_pairs, m_max), dtype=torch.bool)
    f_mask = torch.zeros((n_pairs, f_max), dtype=torch.bool)
    for p, (m, f) in enumerate(zip(movings, fixeds)):
        mov[p, : len(m)] = torch.from_numpy(m)
        fix[p, : len(f)] = torch.from_numpy(f)
        m_mask[p, : len(m)] = True
        f_mask[p, : len(f)] = True
    mov, fix, m_mask, f_mask = mov.to(device), fix.to(device), m_mask.to(device), f_mask.to(device)
    init = torch.from_numpy(np.ascontiguousarray(inits)).to(device)

    def apply(transform, points):
        return points @ transform[:, :3, :3].transpose(1, 2) + transform[:, None, :3, 3]

    def nearest(query, points):
        # Chunked over pairs so that one distance block holds at most about 2**24 entries.
        step = max(1, 2**24 // (query.shape[1] * points.shape[1]))
        parts = [torch.cdist(query[b : b + step], points[b : b + step]).min(dim=2) for b in range(0, n_pairs, step)]
        return torch.cat([d for d, _ in parts]), torch.cat([j for _, j in parts])

    def mean_nn(query, q_mask, points):
        d, _ = nearest(query, points)
        mean = (d * q_mask).sum(1) / q_mask.sum(1).clamp(min=1)
        inliers = ((d < params.inlier_dist) & q_mask).sum(1)
        return mean, inliers

    n_m, n_f = m_mask.sum(1), f_mask.sum(1)
    valid = (n_m > 0) & (n_f > 0)
    err_init, _ = mean_nn(apply(init, mov), m_mask, fix)
    transform = init.clone()
    active = valid.clone()
    prev_rmse = torch.full((n_pairs,), -1.0, dtype=torch.float64, device=device)  # negative: no previous
    iterations = torch.zeros(n_pairs, dtype=torch.long, device=device)
    for _ in range(params.max_iter):
        if not bool(active.any()):
            break
        d, j = nearest(apply(transform, mov), fix)
        w = ((d < params.max_corr) & m_mask).to(torch.float64)
        count = w.sum(1)
        active = active & (count >= 3)
        target = torch.gather(fix, 1, j[..., None].expand(-1, -1, 3))
        cw = count.clamp(min=1)[:, None]
        mean_m = (mov * w[..., None]).sum(1) / cw
        mean_f = (target * w[..., None]).sum(1) / cw
        h = ((mov - mean_m[:, None]) * w[..., None]).transpose(1, 2) @ (target - mean_f[:, None])
        if params.yaw_only:
            angle = torch.atan2(h[:, 0, 1] - h[:, 1, 0], h[:, 0, 0] + h[:, 1, 1])
            rotation = torch.eye(3, dtype=torch.float64, device=device).repeat(n_pairs, 1, 1)
            rotation[:, 0, 0], rotation[:, 0, 1] = torch.cos(angle), -torch.sin(angle)
            rotation[:, 1, 0], rotation[:, 1, 1] = torch.sin(angle), torch.cos(angle)
        else:
            u, _, vt = torch.linalg.svd(h)
            v = vt.transpose(1, 2)
            d_fix = torch.ones((n_pairs, 3), dtype=torch.float64, device=device)
            d_fix[:, 2] = torch.where(torch.linalg.det(v @ u.transpose(1, 2)) < 0, -1.0, 1.0)
            rotation = v @ torch.diag_embed(d_fix) @ u.transpose(1, 2)
        new = torch.eye(4, dtype=torch.float64, device=device).repeat(n_pairs, 1, 1)
        new[:, :3, :3] = rotation
        new[:, :3, 3] = mean_f - (rotation @ mean_m[..., None])[..., 0]
        transform = torch.where(active[:, None, None], new, transform)
        iterations += active.long()
        rmse = (((apply(new, mov) - target).square().sum(2) * w).sum(1) / count.clamp(min=1)).sqrt()
        active = active & ~((prev_rmse >= 0) & (prev_rmse - rmse <= params.rel_rmse * prev_rmse))
        prev_rmse = rmse
    err_fwd, _ = mean_nn(apply(transform, mov), m_mask, fix)
    worse = err_fwd >= err_init
    transform = torch.where(worse[:, None, None], init, transform)
    moved = torch.where(m_mask[..., None], apply(transform, mov), torch.full_like(mov, far))
    err_fwd, inl_fwd = mean_nn(moved, m_mask, fix)
    err_bwd, inl_bwd = mean_nn(torch.where(f_mask[..., None], fix, torch.full_like(fix, -far)), f_mask, moved)
    n_all = (n_m + n_f).to(torch.float64)
    iou = torch.minimum(inl_fwd / (n_all - inl_fwd), inl_bwd / (n_all - inl_bwd))
    error = torch.where(valid, torch.minimum(err_fwd, err_bwd), torch.full_like(err_fwd, float("inf")))
    iou = torch.where(valid, iou, torch.zeros_like(iou))
    transform = torch.where(valid[:, None, None], transform, init)
    return (transform.cpu().numpy(), error.cpu().numpy(), iou.cpu().numpy(), iterations.cpu().numpy())


# ------------------------------------------------------------------------------------------------- entry point


def register_clusters(
    pairs: list[tuple[np.ndarray, np.ndarray]], inits: np.ndarray, cfg=None, backend: str = "cpu",
    params: ICPParams | None = None,
) -> RegistrationResult:
    """Register P cluster pairs (src (Ns, 3), dst (Nd, 3)) from initial src -> dst transforms ``inits`` (P, 4, 4).

    Settings come from ``params`` if given, else from ``cfg`` (an ``ICPFlowConfig``). Each cluster is capped at
    ``max_points`` by a seeded subsample. A pair with an empty cluster keeps its initial transform, with an
    infinite error and a zero IoU ratio.
    """
    params = params or params_from_config(cfg)
    inits = np.asarray(inits, dtype=np.float64).reshape(-1, 4, 4)
    if len(inits) != len(pairs):
        raise ValueError(f"register_clusters: {len(pairs)} pairs but {len(inits)} initial transforms")
    if backend not in ("cpu", "torch"):
        raise ValueError(f"register_clusters: backend must be 'cpu' or 'torch', got {backend!r}")
    n_pairs = len(pairs)
    if n_pairs == 0:
        return RegistrationResult(np.zeros((0, 4, 4)), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    movings, fixeds, starts = [], [], np.empty_like(inits)
    swapped = np.zeros(n_pairs, dtype=bool)
    for p, (src, dst) in enumerate(pairs):
        src = subsample(np.asarray(src, np.float64).reshape(-1, 3), params.max_points, params.seed)
        dst = subsample(np.asarray(dst, np.float64).reshape(-1, 3), params.max_points, params.seed)
        swapped[p] = len(src) > len(dst)  # register the smaller cluster to the larger one
        movings.append(dst if swapped[p] else src)
        fixeds.append(src if swapped[p] else dst)
        starts[p] = invert(inits[p]) if swapped[p] else inits[p]
    if backend == "cpu":
        transforms, errors, ious, iters = _run_batch(movings, fixeds, starts, params)
    else:
        transforms, errors, ious, iters = _register_torch(movings, fixeds, starts, params)
    for p in np.flatnonzero(swapped):
        transforms[p] = invert(transforms[p])
    return RegistrationResult(transforms, errors, ious, iters)
