"""Step 6's ICP variants on one cluster pair (numba), and the ICP settings.

* :func:`icp_point_to_point`: correspondences are each moving point's nearest fixed point within ``max_corr``
  (0.1 m); the update is the closed-form (Kabsch) rigid transform to them, or with ``yaw_only`` (``icp.dof="yaw"``)
  a rotation about z only (angle ``atan2(H01 - H10, H00 + H11)`` of the centred cross-covariance H) and a 3D
  translation; it stops after ``max_iter`` (100) iterations, when the RMSE of an iteration's correspondences after
  its update fell by at most ``rel_rmse`` (1e-6) relative to the previous iteration's (rising counts as converged;
  pytorch3d's ICP, which the reference uses, stops the same way), or with fewer than 3 correspondences.
* :func:`icp_point_to_plane` (the de-skew refinement): each moved source point is paired with its nearest
  destination point within ``max_corr``; the residual is the distance along that point's normal (:func:`normals`:
  smallest principal axis of its ``PLANE_NEIGHBOURS`` nearest neighbours); each iteration solves the linearised
  least-squares update of a rotation about z (through the moved source centroid) and a 3D translation, which does
  not slide along flat sides the way point-to-point ICP does between differently sampled scans; it stops after
  ``PLANE_MAX_ITER`` (30) iterations, when the update is below 1e-4 (rad and m), or with fewer than 4
  correspondences.

Clouds (N, 3) float64 in one frame; transforms (4, 4) float64, moving -> fixed. The settings are
``icpflow.teacher.config.ICPConfig``'s.
"""

from __future__ import annotations

import numba
import numpy as np

from icpflow.scans.neighbours import nearest, transform_cloud
from icpflow.scans.normals import plane_normals

# Neighbours (the point included) whose covariance gives a destination point's normal in point-to-plane ICP.
PLANE_NEIGHBOURS = 10
# Point-to-plane ICP stops when an update turns by less than this (rad) and moves by less than this (m), or after
# ``PLANE_MAX_ITER`` iterations (nearest-neighbour switches can make it cycle at the 0.1 mm level).
_PLANE_TOL = 1e-4
PLANE_MAX_ITER = 30


@numba.njit(cache=True, nogil=True)
def icp_point_to_point(moving, fixed, grid, cell, init, max_corr, max_iter, rel_rmse, yaw_only):
    """Point-to-point ICP of moving (M, 3) onto fixed (N, 3) from ``init``: ((4, 4) transform, iterations run).
    ``grid`` is fixed's ``build_grid`` with cells of ``cell`` metres (any size: the search is exact; cells a few
    times ``max_corr`` answer fastest)."""
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
                    transform[a, 0] * moving[i, 0]
                    + transform[a, 1] * moving[i, 1]
                    + transform[a, 2] * moving[i, 2]
                    + transform[a, 3]
                )
            j, _ = nearest(q, fixed, grid, cell, max_d2)
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
                        transform[a, 0] * moving[i, 0]
                        + transform[a, 1] * moving[i, 1]
                        + transform[a, 2] * moving[i, 2]
                        + transform[a, 3]
                        - fixed[j, a]
                    )
                    sse += r * r
        rmse = np.sqrt(sse / count)
        if prev_rmse >= 0.0 and prev_rmse - rmse <= rel_rmse * prev_rmse:
            break  # the RMSE stopped falling by more than rel_rmse (relative)
        prev_rmse = rmse
    return transform, iterations


@numba.njit(cache=True, nogil=True)
def icp_point_to_plane(moving, fixed, normals, grid, cell, init, max_corr, max_iter):
    """Point-to-plane ICP (rotation about z and 3D translation) of moving (M, 3) onto fixed (N, 3) with unit
    ``normals`` (N, 3), from ``init``: ((4, 4) transform, iterations run). ``grid``/``cell`` as in
    :func:`icp_point_to_point`."""
    transform = init.copy()
    max_d2 = max_corr * max_corr
    iterations = 0
    while iterations < max_iter:
        moved = transform_cloud(moving, transform)
        centre = np.zeros(3)
        for i in range(moved.shape[0]):
            centre += moved[i]
        centre /= moved.shape[0]
        ata = np.zeros((4, 4))
        atb = np.zeros(4)
        row = np.empty(4)
        count = 0
        for i in range(moved.shape[0]):
            j, _ = nearest(moved[i], fixed, grid, cell, max_d2)
            if j < 0:
                continue
            n = normals[j]
            residual = (
                (moved[i, 0] - fixed[j, 0]) * n[0]
                + (moved[i, 1] - fixed[j, 1]) * n[1]
                + (moved[i, 2] - fixed[j, 2]) * n[2]
            )
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
    return plane_normals(points, nearest)
