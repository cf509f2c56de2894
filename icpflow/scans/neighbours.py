"""Exact nearest neighbours in small clouds (the ICP correspondences and the match quality of step 6).

:func:`build_grid` sorts a cloud (N, 3) into a voxel grid (columns in xy, z cells within a column);
:func:`nearest` answers one query exactly by visiting cubic shells of cells around it, nearest first, falling back
to a full scan when the query is far from the cloud. :func:`nn_stats` gives the mean nearest-neighbour distance and
inlier count of a whole query cloud; :func:`transform_cloud` maps a cloud by a (4, 4) transform. All numba, metres,
one shared frame. :func:`k_nearest` gives the k nearest of many queries (the odometry's target normals and fits).
"""

from __future__ import annotations

import numba
import numpy as np

# Grid shells searched before a nearest-neighbour query falls back to scanning every point.
_MAX_SHELL = 3
# Squared distances at or above this are "nothing found yet" (no z-range pruning).
_FAR = 1e30
# Shells a k-nearest query visits before it scans every point (the 10th neighbour of an odometry target's point lies
# within 3.5 m for 99 % of them, 7 shells of 0.5 m cells; docs/history.md, "The odometry's normals: far queries on a
# coarse grid (point 3)").
MAX_KNN_SHELL = 8
#: the indices of a k-nearest query that gave up (``k_nearest`` without ``scan_all``)
GAVE_UP = -2


#: the most xy columns (and z cells) a grid of n points spans beyond ``GRID_CELLS_PER_POINT * n``: a cloud whose
#: bounding box would need more (stray returns kilometres out) gets a box of this size around its median, its
#: outlying points in the border cells, so that memory follows the number of points, not where they are
GRID_MIN_CELLS = 1 << 20
GRID_CELLS_PER_POINT = 4


@numba.njit(cache=True, nogil=True)
def build_grid(points, cell):
    """Voxel grid of (N, 3) points, sorted by xy column then z cell: (origin (3,), dims (4,): cells along x, y, z and
    1 where the box is narrower than the points' (0 else), column starts (nx * ny + 1,), z cell of each sorted point
    (N,), sorted point order (N,)).

    The box is the points' bounding box, unless its columns or z cells would exceed ``GRID_CELLS_PER_POINT`` per
    point (at least ``GRID_MIN_CELLS``): then each such axis spans that many cells around the points' median, and a
    point beyond sits in the border cell. Searches stay exact: such a point is farther than its cell says, which no
    pruning relies on, and a query outside a narrowed box scans every point (:func:`nearest`)."""
    n = points.shape[0]
    most = max(GRID_MIN_CELLS, GRID_CELLS_PER_POINT * n)
    side = int(np.sqrt(most))
    origin = np.empty(3)
    dims = np.zeros(4, dtype=np.int64)
    for a in range(3):
        lo, hi = points[:, a].min(), points[:, a].max()
        origin[a] = lo
        dims[a] = int((hi - lo) / cell) + 1
    if dims[0] * dims[1] > most or dims[2] > most:
        dims[3] = 1
        for a in range(3):
            bound = side if a < 2 else most
            if dims[a] > bound:
                origin[a] = max(points[:, a].min(), np.median(points[:, a]) - 0.5 * bound * cell)
                dims[a] = bound
    columns = np.empty(n, dtype=np.int64)
    z_cells = np.empty(n, dtype=np.int64)
    for i in range(n):
        cx = min(max(int((points[i, 0] - origin[0]) / cell), 0), dims[0] - 1)
        cy = min(max(int((points[i, 1] - origin[1]) / cell), 0), dims[1] - 1)
        z_cells[i] = min(max(int((points[i, 2] - origin[2]) / cell), 0), dims[2] - 1)
        columns[i] = cx * dims[1] + cy
    # a stable sort by (column, z cell): by z cell, then by column, both counting sorts (a stable argsort of the
    # combined key gives the same order, 7x slower on 40k points)
    z_starts = np.zeros(dims[2] + 1, dtype=np.int64)
    for i in range(n):
        z_starts[z_cells[i] + 1] += 1
    for k in range(1, z_starts.shape[0]):
        z_starts[k] += z_starts[k - 1]
    by_z = np.empty(n, dtype=np.int64)
    for i in range(n):
        by_z[z_starts[z_cells[i]]] = i
        z_starts[z_cells[i]] += 1
    starts = np.zeros(dims[0] * dims[1] + 1, dtype=np.int64)
    for i in range(n):
        starts[columns[i] + 1] += 1
    for k in range(1, starts.shape[0]):
        starts[k] += starts[k - 1]
    order = np.empty(n, dtype=np.int64)
    filled = starts[:-1].copy()
    for i in by_z:
        order[filled[columns[i]]] = i
        filled[columns[i]] += 1
    return origin, dims, starts, z_cells[order], order


@numba.njit(cache=True, nogil=True)
def _column_from(starts, z_sorted, column, z0):
    """The sorted index of grid column ``column``'s first point at z cell >= z0 (a binary search: tall columns hold
    many points)."""
    lo, hi = starts[column], starts[column + 1]
    while lo < hi:
        mid = (lo + hi) // 2
        if z_sorted[mid] < z0:
            lo = mid + 1
        else:
            hi = mid
    return lo


@numba.njit(cache=True, nogil=True)
def _scan_column(q, points, starts, z_sorted, order, dims, cx, cy, z0, z1, best_d2, best_j):
    """Closest point to q among grid column (cx, cy), z cells z0..z1 (already clipped)."""
    column = cx * dims[1] + cy
    for s in range(_column_from(starts, z_sorted, column, z0), starts[column + 1]):
        if z_sorted[s] > z1:
            break
        j = order[s]
        d2 = (points[j, 0] - q[0]) ** 2 + (points[j, 1] - q[1]) ** 2 + (points[j, 2] - q[2]) ** 2
        if d2 < best_d2:
            best_d2, best_j = d2, j
    return best_d2, best_j


@numba.njit(cache=True, nogil=True)
def _nearest_brute(q, points, max_d2):
    """Nearest of ``points`` to q by a full scan: (index, squared distance), or (-1, max_d2)."""
    best_d2, best_j = max_d2, -1
    for j in range(points.shape[0]):
        d2 = (points[j, 0] - q[0]) ** 2 + (points[j, 1] - q[1]) ** 2 + (points[j, 2] - q[2]) ** 2
        if d2 < best_d2:
            best_d2, best_j = d2, j
    return best_j, best_d2


@numba.njit(cache=True, nogil=True)
def nearest(q, points, grid, cell, max_d2):
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
    if dims[3] and gap > 0:
        return _nearest_brute(q, points, max_d2)  # outside a narrowed box: its border cells hold points beyond it
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
                        best_d2, best_j = _scan_column(
                            q, points, starts, z_sorted, order, dims, cx, cy, z_from, z_to, best_d2, best_j
                        )
                else:  # inside the shell's xy square: only its bottom and top cells belong to shell r
                    if z_from <= c2 - r <= z_to:
                        best_d2, best_j = _scan_column(
                            q, points, starts, z_sorted, order, dims, cx, cy, c2 - r, c2 - r, best_d2, best_j
                        )
                    if z_from <= c2 + r <= z_to:
                        best_d2, best_j = _scan_column(
                            q, points, starts, z_sorted, order, dims, cx, cy, c2 + r, c2 + r, best_d2, best_j
                        )
        r += 1
    return best_j, best_d2


@numba.njit(cache=True, nogil=True)
def _keep(d2, j, best_d2, best_j):
    """Insert point j at squared distance d2 into the ascending (k,) lists ``best_d2``, ``best_j`` if it is closer
    than their last (an equal distance keeps the point found first)."""
    last = best_d2.shape[0] - 1
    if d2 >= best_d2[last]:
        return
    at = last
    while at > 0 and best_d2[at - 1] > d2:
        best_d2[at] = best_d2[at - 1]
        best_j[at] = best_j[at - 1]
        at -= 1
    best_d2[at] = d2
    best_j[at] = j


@numba.njit(cache=True, nogil=True)
def _scan_column_k(q, points, starts, z_sorted, order, dims, cx, cy, z0, z1, best_d2, best_j):
    """``_scan_column`` for the k nearest: the points of column (cx, cy), z cells z0..z1, kept in the lists."""
    column = cx * dims[1] + cy
    for s in range(_column_from(starts, z_sorted, column, z0), starts[column + 1]):
        if z_sorted[s] > z1:
            break
        j = order[s]
        _keep((points[j, 0] - q[0]) ** 2 + (points[j, 1] - q[1]) ** 2 + (points[j, 2] - q[2]) ** 2, j, best_d2, best_j)


@numba.njit(cache=True, nogil=True)
def _k_nearest_all(q, points, best_d2, best_j):
    """The k nearest of every point to q into ``best_d2`` / ``best_j``, started again: below the caller's max_d2 (still
    the last entry where fewer than k were found; where k were, the k nearest are nearer than it anyway)."""
    k = best_d2.shape[0]
    limit = best_d2[k - 1] if best_j[k - 1] < 0 else np.inf
    best_d2[:] = limit
    best_j[:] = -1
    for j in range(points.shape[0]):
        _keep((points[j, 0] - q[0]) ** 2 + (points[j, 1] - q[1]) ** 2 + (points[j, 2] - q[2]) ** 2, j, best_d2, best_j)


@numba.njit(cache=True, nogil=True)
def _k_nearest_one(q, points, grid, cell, best_d2, best_j, max_shell, scan_all):
    """The k nearest of ``points`` to q into ``best_d2`` / ``best_j`` (k,), which hold (max_d2, -1) on entry: the
    search of :func:`nearest`, pruned by the k-th distance so far; beyond ``max_shell`` shells a full scan
    (``scan_all``) or ``GAVE_UP`` in ``best_j``."""
    origin, dims, starts, z_sorted, order = grid
    k = best_d2.shape[0]
    c0 = int(np.floor((q[0] - origin[0]) / cell))
    c1 = int(np.floor((q[1] - origin[1]) / cell))
    c2 = int(np.floor((q[2] - origin[2]) / cell))
    gap = max(0, -c0, c0 - (dims[0] - 1), -c1, c1 - (dims[1] - 1), -c2, c2 - (dims[2] - 1))
    if dims[3] and gap > 0:  # outside a narrowed box: its border cells hold points beyond it
        _k_nearest_all(q, points, best_d2, best_j)
        return
    if gap > 1 and ((gap - 1) * cell) ** 2 >= best_d2[k - 1]:
        return
    r = gap
    r_max = gap + max(dims[0], dims[1], dims[2])
    while r <= r_max:
        if r > 1 and ((r - 1) * cell) ** 2 >= best_d2[k - 1]:
            break
        if r > max_shell:
            if not scan_all:
                best_j[:] = GAVE_UP
                return
            _k_nearest_all(q, points, best_d2, best_j)
            return
        z_lo, z_hi = max(c2 - r, 0), min(c2 + r, dims[2] - 1)
        for cx in range(max(c0 - r, 0), min(c0 + r, dims[0] - 1) + 1):
            gx = max(0.0, origin[0] + cx * cell - q[0], q[0] - origin[0] - (cx + 1) * cell)
            if gx * gx >= best_d2[k - 1]:
                continue
            for cy in range(max(c1 - r, 0), min(c1 + r, dims[1] - 1) + 1):
                gy = max(0.0, origin[1] + cy * cell - q[1], q[1] - origin[1] - (cy + 1) * cell)
                gxy2 = gx * gx + gy * gy
                worst = best_d2[k - 1]
                if gxy2 >= worst:
                    continue
                z_from, z_to = z_lo, z_hi
                if worst < _FAR:
                    reach = np.sqrt(worst - gxy2)
                    z_from = max(z_lo, int(np.floor((q[2] - reach - origin[2]) / cell)))
                    z_to = min(z_hi, int(np.floor((q[2] + reach - origin[2]) / cell)))
                if abs(cx - c0) == r or abs(cy - c1) == r:
                    if z_from <= z_to:
                        _scan_column_k(q, points, starts, z_sorted, order, dims, cx, cy, z_from, z_to, best_d2, best_j)
                else:
                    if z_from <= c2 - r <= z_to:
                        _scan_column_k(
                            q, points, starts, z_sorted, order, dims, cx, cy, c2 - r, c2 - r, best_d2, best_j
                        )
                    if z_from <= c2 + r <= z_to:
                        _scan_column_k(
                            q, points, starts, z_sorted, order, dims, cx, cy, c2 + r, c2 + r, best_d2, best_j
                        )
        r += 1


@numba.njit(cache=True, nogil=True, parallel=True)
def k_nearest(query, points, grid, cell, k, max_d2, max_shell, scan_all):
    """The ``k`` nearest of ``points`` (N, 3) (with their ``build_grid``) to each query point (M, 3), exactly:
    (squared distances (M, k) ascending, indices (M, k) int64); ``max_d2`` where fewer than k lie closer than
    sqrt(``max_d2``), index -1 there. A query whose k-th neighbour lies beyond ``max_shell`` shells of cells
    (``MAX_KNN_SHELL``: the grid's) scans every point where ``scan_all``, else its indices are ``GAVE_UP`` (the
    caller asks a coarser grid). The queries run on numba's threads (the caller's setting)."""
    best_d2 = np.full((query.shape[0], k), max_d2)
    best_j = np.full((query.shape[0], k), -1, dtype=np.int64)
    if points.shape[0] == 0:
        return best_d2, best_j
    for i in numba.prange(query.shape[0]):
        _k_nearest_one(query[i], points, grid, cell, best_d2[i], best_j[i], max_shell, scan_all)
    return best_d2, best_j


@numba.njit(cache=True, nogil=True)
def transform_cloud(points, transform):
    """(N, 3) points mapped by a (4, 4) transform."""
    out = np.empty_like(points)
    for i in range(points.shape[0]):
        for a in range(3):
            out[i, a] = (
                transform[a, 0] * points[i, 0]
                + transform[a, 1] * points[i, 1]
                + transform[a, 2] * points[i, 2]
                + transform[a, 3]
            )
    return out


@numba.njit(cache=True, nogil=True)
def nn_stats(query, points, grid, cell, inlier_d2):
    """Exact nearest-neighbour distances from query (M, 3) to points (N, 3) with their ``build_grid``:
    (mean distance, inlier count)."""
    total = 0.0
    inliers = 0
    for i in range(query.shape[0]):
        _, d2 = nearest(query[i], points, grid, cell, np.inf)
        total += np.sqrt(d2)
        if d2 < inlier_d2:
            inliers += 1
    return total / query.shape[0], inliers


@numba.njit(cache=True, nogil=True)
def nearest_distances(query, points, grid, cell, reach):
    """(M,) exact distances from each query point (M, 3) to its nearest of points (N, 3) with their ``build_grid``,
    where it lies nearer than ``reach`` (M,) m (inf: any distance), inf elsewhere: a bounded query stops at its reach
    (the refinement asks whether a point lies nearer than a known distance)."""
    out = np.empty(query.shape[0])
    for i in range(query.shape[0]):
        found, d2 = nearest(query[i], points, grid, cell, reach[i] * reach[i])
        out[i] = np.sqrt(d2) if found >= 0 else np.inf
    return out
