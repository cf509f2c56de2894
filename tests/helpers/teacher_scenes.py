"""Small hand-built scenes for the teacher tests: boxes on a ground plane, some moved by known rigid motions."""

from __future__ import annotations

import numpy as np

from icpflow.core.geometry import invert, make_transform, transform_points


def box_surface(size, rng, spacing: float = 0.08) -> np.ndarray:
    """Points on the four vertical faces and the top of a box of ``size`` (l, w, h) with its base centre at 0."""
    length, width, height = size
    faces = []
    for u_len, v_len, place in (
        (length, height, lambda u, v: np.stack([u - length / 2, np.full_like(u, -width / 2), v], 1)),
        (length, height, lambda u, v: np.stack([u - length / 2, np.full_like(u, width / 2), v], 1)),
        (width, height, lambda u, v: np.stack([np.full_like(u, -length / 2), u - width / 2, v], 1)),
        (width, height, lambda u, v: np.stack([np.full_like(u, length / 2), u - width / 2, v], 1)),
        (length, width, lambda u, v: np.stack([u - length / 2, v - width / 2, np.full_like(u, height)], 1)),
    ):
        count = max(4, int(u_len * v_len / spacing**2))
        faces.append(place(rng.uniform(0, u_len, count), rng.uniform(0, v_len, count)))
    return np.concatenate(faces)


MOVING_BOX_MOTIONS = (make_transform(yaw=0.05, translation=(1.2, 0.3, 0.0)),)


def scene(ego1_from_ego0=None, seed: int = 0, moving=MOVING_BOX_MOTIONS):
    """Two scans of a scene in their ego frames, with the exact full flow of pc0.

    Boxes (l, w, h) at fixed places; the first ``len(moving)`` boxes move by the given motions (in the ego frame
    of t); a flat ground grid at z = 0. Returns dict(pc0, pc1, flow, ego, moving0 (N0,) bool, ground0, ground1).
    """
    rng = np.random.default_rng(seed)
    ego = np.eye(4) if ego1_from_ego0 is None else np.asarray(ego1_from_ego0, np.float64)
    boxes = [
        ((4.5, 1.9, 1.6), (8.0, 3.0, 0.25)),
        ((4.0, 1.8, 1.5), (-6.0, -4.0, 0.25)),
        ((2.0, 2.0, 3.0), (3.0, -8.0, 0.25)),
        ((6.0, 1.0, 2.0), (-10.0, 6.0, 0.25)),
        ((1.0, 1.0, 2.5), (12.0, -5.0, 0.25)),
    ]
    pc0, pc1, flow, moving0 = [], [], [], []
    for index, (size, (x, y, z)) in enumerate(boxes):
        place = make_transform(yaw=0.3 * index, translation=(x, y, z))
        motion = moving[index] if index < len(moving) else np.eye(4)
        # motion is about the box centre, expressed in the ego frame of t
        world_motion = place @ motion @ invert(place)
        p0 = transform_points(place, box_surface(size, rng).astype(np.float32))
        p1 = transform_points(ego @ world_motion @ place, box_surface(size, rng).astype(np.float32))
        pc0.append(p0)
        pc1.append(p1)
        flow.append(transform_points(ego @ world_motion, p0) - p0)
        moving0.append(np.full(len(p0), index < len(moving)))
    grid = np.stack(np.meshgrid(np.arange(-20, 20, 0.5), np.arange(-20, 20, 0.5)), -1).reshape(-1, 2)
    ground = np.concatenate([grid, np.zeros((len(grid), 1))], 1).astype(np.float32)
    ground0 = ground + rng.normal(0, 0.01, ground.shape).astype(np.float32)
    ground1 = transform_points(ego, ground + rng.normal(0, 0.01, ground.shape).astype(np.float32))
    pc0 = np.concatenate(pc0 + [ground0]).astype(np.float32)
    pc1 = np.concatenate(pc1 + [ground1]).astype(np.float32)
    flow = np.concatenate(flow + [transform_points(ego, ground0) - ground0]).astype(np.float32)
    n_ground0, n_ground1 = len(ground0), len(ground1)
    return {
        "pc0": pc0,
        "pc1": pc1,
        "flow": flow,
        "ego": ego,
        "moving0": np.concatenate(moving0 + [np.zeros(n_ground0, bool)]),
        "ground0": np.r_[np.zeros(len(pc0) - n_ground0, bool), np.ones(n_ground0, bool)],
        "ground1": np.r_[np.zeros(len(pc1) - n_ground1, bool), np.ones(n_ground1, bool)],
    }
