"""What the tests of an exported tiny model share (``tests/fastflow3d/conftest.py`` builds the model): eager flow,
scan and pose files, a lowered pair, crowded points, the flat teacher dict of older checkpoints."""

from pathlib import Path

import numpy as np
import torch

from fastflow3d.network.model import compensate
from icpflow.core.geometry import residual_to_full
from icpflow.core.open3d_loader import load_open3d
from icpflow.scans.preprocess import lift_points, lift_transform

from helpers.training import TINY_MODEL

NEAR = TINY_MODEL["x_range"][1] + 0.6  # m: points this far from the sensor (x and y) are near the grid


TOLERANCE = 1e-4  # metres


def eager_full_flow(net, pair):
    with torch.no_grad():
        residual, valid = net(torch.from_numpy(compensate(pair.pc0, pair.ego1_from_ego0)), torch.from_numpy(pair.pc1))
    return residual_to_full(residual.numpy(), pair.pc0, pair.ego1_from_ego0), valid.numpy()


#: the flat ICPFlowConfig fields that checkpoints of older versions saved as ``data.teacher`` (before the typed
#: block and the teacher's ground / ego_motion blocks), with the synthetic dataset's values
LEGACY_TEACHER = dict(ground="both", sensor_height=1.9, patchwork_max_range=64.0, patchwork_z_offset=-1.9, range_z=0.04)


def write_scan(path: Path, points: np.ndarray) -> Path:
    """Write (N, 3) float32 points in the format of ``path``'s suffix."""
    suffix = path.suffix
    if suffix == ".bin":
        np.c_[points, np.ones(len(points))].astype(np.float32).tofile(path)
    elif suffix == ".npy":
        np.save(path, points)
    elif suffix == ".npz":
        np.savez(path, points=points)
    else:
        o3d = load_open3d()
        o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(float))))
    return path


def write_poses(path: Path, poses) -> Path:
    path.write_text("".join(" ".join(f"{v:.12g}" for v in pose[:3].ravel()) + "\n" for pose in poses))
    return path


def crowded_points(seed: int = 1):
    """Two scans of 60,000 and 40,000 points in 150 pillars of the tiny grid (many points per pillar)."""
    rng = np.random.default_rng(seed)
    cells = rng.uniform(-15.0, 15.0, (150, 2))
    scans = []
    for count in (60_000, 40_000):
        xy = cells[rng.integers(0, len(cells), count)] + rng.uniform(-0.05, 0.05, (count, 2))
        scans.append(np.column_stack([xy, rng.uniform(0.3, 2.0, count)]).astype(np.float32))
    return scans


# ------------------------------------------------------------------------------------- height frame, bare files
def lowered(pair, height: float):
    """pc0, pc1 and ego1_from_ego0 of ``pair`` as a sensor ``height`` m above its ground would give them (the
    KITTI velodyne convention: ground near z = -height)."""
    return lift_points(pair.pc0, -height), lift_points(pair.pc1, -height), lift_transform(pair.ego1_from_ego0, -height)
