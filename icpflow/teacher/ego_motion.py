"""Step 1: ego motion ``ego1_from_ego0`` between two scans: KISS-ICP (``kiss-icp`` 1.x public API), then an
optional point-to-plane refinement (open3d ``registration_icp``) of the KISS-ICP estimate.

KISS-ICP is built for sequences; on a single pair its adaptive threshold starts wide and its map holds one scan,
which leaves a few centimetres of error on KITTI. The refinement (``ego_motion.refine_voxel`` > 0) aligns the two scans
directly, point-to-plane, from the KISS-ICP estimate.

Settings: the teacher's ``ego_motion`` block (``icpflow.teacher.config.EgoMotionConfig``), or a ``Preprocessing``
or a teacher config holding it (:func:`ego_settings`).
"""

from __future__ import annotations

import numpy as np

from icpflow.geometry import invert
from icpflow.preprocess import Preprocessing
from icpflow.teacher.config import EgoMotionConfig


def ego_settings(cfg) -> EgoMotionConfig:
    """The ego-motion settings of ``cfg``: an EgoMotionConfig, or a Preprocessing / teacher config holding one (a
    dict of teacher fields, older flat names included, is read by ``Preprocessing.from_teacher``)."""
    if isinstance(cfg, EgoMotionConfig):
        return cfg
    if isinstance(getattr(cfg, "ego_motion", None), EgoMotionConfig):
        return cfg.ego_motion
    return Preprocessing.from_teacher(cfg).ego_motion


def kiss_odometry(cfg):
    """A fresh ``kiss_icp.kiss_icp.KissICP`` with ``cfg``'s ego-motion settings (max range, voxel size), deskewing off
    (no per-point timestamps)."""
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    config = load_config(None)
    config.data.deskew = False
    settings = ego_settings(cfg)
    config.data.max_range = float(settings.kiss_max_range)
    config.mapping.voxel_size = float(settings.kiss_voxel_size)
    return KissICP(config)


def kiss_icp_motion(pc0: np.ndarray, pc1: np.ndarray, cfg) -> np.ndarray:
    """(4, 4) float64 ``ego1_from_ego0`` by KISS-ICP: pc0 is registered first (its pose becomes the identity), then
    pc1 against the map of pc0; pc1's pose is ``ego0_from_ego1``."""
    odometry = kiss_odometry(cfg)
    empty = np.zeros(0)
    odometry.register_frame(np.asarray(pc0, np.float64), empty)
    odometry.register_frame(np.asarray(pc1, np.float64), empty)
    return invert(np.asarray(odometry.last_pose, dtype=np.float64))


def refine_motion(pc0: np.ndarray, pc1: np.ndarray, ego1_from_ego0: np.ndarray, cfg) -> np.ndarray:
    """Point-to-plane ICP of pc0 onto pc1 from ``ego1_from_ego0``, on ``refine_voxel`` down-sampled scans."""
    import open3d as o3d

    voxel = float(ego_settings(cfg).refine_voxel)
    clouds = []
    for points in (pc0, pc1):
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
        clouds.append(cloud.voxel_down_sample(voxel))
    clouds[1].estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=20))
    result = o3d.pipelines.registration.registration_icp(
        clouds[0],
        clouds[1],
        2.0 * voxel,
        ego1_from_ego0,
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=50),
    )
    transform = np.asarray(result.transformation, dtype=np.float64)
    return transform if result.fitness > 0.3 else ego1_from_ego0


#: fewer points than this in either scan: no estimate (the identity)
MIN_EGO_POINTS = 100


def estimate_ego_motion(pc0: np.ndarray, pc1: np.ndarray, cfg) -> np.ndarray:
    """(4, 4) float64 ``ego1_from_ego0`` of (N0, 3) and (N1, 3) scans; identity if either has fewer than
    ``MIN_EGO_POINTS`` points."""
    if len(pc0) < MIN_EGO_POINTS or len(pc1) < MIN_EGO_POINTS:
        return np.eye(4)
    transform = kiss_icp_motion(pc0, pc1, cfg)
    if ego_settings(cfg).refine_voxel > 0:
        transform = refine_motion(pc0, pc1, transform, cfg)
    return transform
