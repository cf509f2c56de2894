"""Rigid transforms and the project's flow conventions, written once.

Frames and units
----------------
* Points are metres, float32, shape (N, 3), expressed in the ego (vehicle) frame of their own scan.
* A transform ``b_from_a`` is a (4, 4) float64 homogeneous rigid matrix mapping coordinates in frame ``a`` to
  frame ``b``: ``p_b = R p_a + t``. Poses are ``world_from_ego``.
* ``ego1_from_ego0`` maps the ego frame of scan t (pc0) into the ego frame of scan t + dt (pc1).

Flow convention
---------------
* FULL flow (what the project stores everywhere): ``pc0 + flow`` is each pc0 point's position at t + dt,
  expressed in the ego frame of t + dt. This is the Argoverse 2 convention; it includes the ego motion.
* EGO flow: the full flow a point would have if it were static, ``ego1_from_ego0 * p - p``.
* RESIDUAL (ego-compensated) flow: ``full - ego``; zero for static points.
"""

from __future__ import annotations

import numpy as np

ROTATION_ATOL = 1e-4


def is_rigid(transform: np.ndarray, atol: float = ROTATION_ATOL) -> bool:
    """True if ``transform`` is a finite (4, 4) rigid transform: orthonormal rotation with det +1, last row 0 0 0 1."""
    transform = np.asarray(transform)
    if transform.shape != (4, 4) or not np.all(np.isfinite(transform)):
        return False
    rotation = transform[:3, :3].astype(np.float64)
    return (
        np.allclose(rotation @ rotation.T, np.eye(3), atol=atol)
        and abs(np.linalg.det(rotation) - 1.0) < atol
        and np.allclose(transform[3], [0.0, 0.0, 0.0, 1.0], atol=atol)
    )


def rigid_problem(transform: np.ndarray, atol: float = ROTATION_ATOL) -> str | None:
    """Why ``transform`` is not a (4, 4) rigid transform, or None if it is one."""
    transform = np.asarray(transform)
    if transform.shape != (4, 4):
        return f"must have shape (4, 4), got {transform.shape}"
    if not np.all(np.isfinite(transform)):
        return "has non-finite entries"
    if not is_rigid(transform, atol):
        return "is not rigid (rotation not orthonormal with det +1, or last row not 0 0 0 1)"
    return None


def lengths(vectors: np.ndarray) -> np.ndarray:
    """(N,) Euclidean length of each of the (N, 3) ``vectors``, in their dtype: ``np.linalg.norm(vectors, axis=1)``
    bit for bit (the same squares summed in the same order, x + y first), a sixth of its time on a scan's flow
    of 73k rows (numpy reduces along the short axis)."""
    x, y, z = vectors[:, 0], vectors[:, 1], vectors[:, 2]
    return np.sqrt(x * x + y * y + z * z)


def orthonormalized(transform: np.ndarray) -> np.ndarray:
    """The (4, 4) float64 rigid transform nearest ``transform``: its rotation block replaced by the nearest rotation
    (the polar factor of its SVD), its translation kept. Products of rigid transforms drift from orthonormal by
    rounding, which some libraries refuse (KISS-ICP's Sophus checks to about 1e-13)."""
    transform = np.asarray(transform, dtype=np.float64)
    u, _, vt = np.linalg.svd(transform[:3, :3])
    out = np.eye(4)
    out[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    out[:3, 3] = transform[:3, 3]
    return out


def invert(transform: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform, float64."""
    transform = np.asarray(transform, dtype=np.float64)
    inverse = np.eye(4)
    inverse[:3, :3] = transform[:3, :3].T
    inverse[:3, 3] = -transform[:3, :3].T @ transform[:3, 3]
    return inverse


def _affine(points: np.ndarray, matrix: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """(N, 3) float64 ``points @ matrix.T + offset`` column by column: a BLAS matmul of an (N, 3) by a (3, 3)
    wakes BLAS's threads, which on a busy 2-core machine costs 60 ms for 100k points against under 1 ms here."""
    points = np.asarray(points, dtype=np.float64)
    flat = points.reshape(-1, 3)
    out = np.empty_like(flat)
    for row in range(3):
        out[:, row] = flat[:, 0] * matrix[row, 0] + flat[:, 1] * matrix[row, 1]
        out[:, row] += flat[:, 2] * matrix[row, 2] + offset[row]
    return out.reshape(points.shape)


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to (N, 3) points; computed in float64, returned in the points' float dtype."""
    points = np.asarray(points)
    transform = np.asarray(transform, dtype=np.float64)
    out = _affine(points, transform[:3, :3], transform[:3, 3])
    return out.astype(points.dtype if np.issubdtype(points.dtype, np.floating) else np.float64)


def relative_transform(pose0: np.ndarray, pose1: np.ndarray) -> np.ndarray:
    """``ego1_from_ego0 = inv(world_from_ego1) @ world_from_ego0`` from two ego-to-world poses."""
    return invert(pose1) @ np.asarray(pose0, dtype=np.float64)


def ego_flow(points: np.ndarray, ego1_from_ego0: np.ndarray) -> np.ndarray:
    """Full flow of static points: ``ego1_from_ego0 * p - p``. (N, 3) in the frame of t -> (N, 3) float32."""
    transform = np.asarray(ego1_from_ego0, dtype=np.float64)
    return _affine(points, transform[:3, :3] - np.eye(3), transform[:3, 3]).astype(np.float32)


def full_to_residual(flow: np.ndarray, pc0: np.ndarray, ego1_from_ego0: np.ndarray) -> np.ndarray:
    """Ego-compensated flow from full flow: ``flow - ego_flow(pc0)``. Both (N, 3) float32."""
    return (np.asarray(flow, np.float64) - ego_flow(pc0, ego1_from_ego0)).astype(np.float32)


def residual_to_full(residual: np.ndarray, pc0: np.ndarray, ego1_from_ego0: np.ndarray) -> np.ndarray:
    """Full flow from ego-compensated flow: ``residual + ego_flow(pc0)``. Both (N, 3) float32."""
    return (np.asarray(residual, np.float64) + ego_flow(pc0, ego1_from_ego0)).astype(np.float32)


def rigid_flow(points: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """Flow of points moved by a rigid transform expressed in their own frame: ``T p - p``, (N, 3) float32."""
    return ego_flow(points, transform)


def kabsch(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(4, 4) float64 rigid transform T minimising ``sum ||T source_i - target_i||^2`` over corresponding (N, 3)
    points (N >= 3; the closed-form SVD solution, reflections excluded)."""
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    mean_s, mean_t = source.mean(axis=0), target.mean(axis=0)
    u, _, vt = np.linalg.svd((source - mean_s).T @ (target - mean_t))
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T)) or 1.0])
    transform = np.eye(4)
    transform[:3, :3] = vt.T @ flip @ u.T
    transform[:3, 3] = mean_t - transform[:3, :3] @ mean_s
    return transform


def make_transform(yaw: float = 0.0, translation=(0.0, 0.0, 0.0), roll: float = 0.0, pitch: float = 0.0) -> np.ndarray:
    """(4, 4) float64 rigid transform from Z-Y-X Euler angles (radians) and a translation (metres)."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    transform = np.eye(4)
    transform[:3, :3] = np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )
    transform[:3, 3] = translation
    return transform


def euler_angles(transform: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in radians of the rotation of a (4, 4) transform (Z-Y-X convention, as make_transform)."""
    rotation = np.asarray(transform, dtype=np.float64)[:3, :3]
    pitch = float(np.arcsin(np.clip(-rotation[2, 0], -1.0, 1.0)))
    roll = float(np.arctan2(rotation[2, 1], rotation[2, 2]))
    yaw = float(np.arctan2(rotation[1, 0], rotation[0, 0]))
    return roll, pitch, yaw


def pose_error(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(translation metres, rotation degrees) of ``inv(truth) @ estimate`` for two (4, 4) transforms: how far an
    estimated transform is from the true one."""
    delta = invert(truth) @ np.asarray(estimate, dtype=np.float64)
    angle = np.degrees(np.arccos(np.clip((np.trace(delta[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(delta[:3, 3])), float(angle)
