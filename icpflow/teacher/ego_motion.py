"""Step 1: ego motion ``ego1_from_ego0`` between two scans: KISS-ICP (``kiss-icp`` 1.x public API), then an
optional point-to-plane refinement (open3d ``registration_icp``) of the KISS-ICP estimate.

KISS-ICP is built for sequences; on a single pair its adaptive threshold starts wide and its map holds one scan,
which leaves a few centimetres of error on KITTI. The refinement (``ego_motion.refine_voxel`` > 0) aligns the two scans
directly, point-to-plane, from the KISS-ICP estimate.

Settings: the teacher's ``ego_motion`` block (``icpflow.teacher.config.EgoMotionConfig``), or a ``Preprocessing``
or a teacher config holding it (:func:`ego_settings`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from icpflow.geometry import invert, plane_normals, transform_points
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
    voxel = float(ego_settings(cfg).refine_voxel)
    source, target = refinement_cloud(pc0, voxel), refinement_cloud(pc1, voxel, normals=True)
    return refine_clouds(source, target, ego1_from_ego0, voxel)[0]


def refinement_cloud(points: np.ndarray, voxel: float, normals: bool = False):
    """The open3d cloud of ``points`` (N, 3) down-sampled to ``voxel`` m (one measured point per voxel, KISS-ICP's
    voxel grid: 4x quicker than open3d's centroids), with normals when it is a refinement's target (of the points
    within ``4 * voxel``, at most 20)."""
    import open3d as o3d
    from kiss_icp.voxelization import voxel_down_sample

    kept = voxel_down_sample(np.asarray(points, np.float64), voxel)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(kept))
    if normals:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=20))
    return cloud


def refine_clouds(
    source, target, transform: np.ndarray, voxel: float, iterations: int = 50, tukey: float | None = None
) -> tuple[np.ndarray, float]:
    """Point-to-plane ICP of the :func:`refinement_cloud` ``source`` onto ``target`` (with normals), both of
    ``voxel`` m, from ``transform`` (correspondences within twice the voxel, at most ``iterations``): the refined
    transform (``transform`` itself when under 30 % of the source finds a correspondence) and that fraction (the
    fitness). ``tukey``: a robust Tukey kernel of that width (m), which leaves moving objects out of the fit."""
    import open3d as o3d

    result = o3d.pipelines.registration.registration_icp(
        source,
        target,
        2.0 * voxel,
        transform,
        o3d.pipelines.registration.TransformationEstimationPointToPlane(
            *([] if tukey is None else [o3d.pipelines.registration.TukeyLoss(k=tukey)])
        ),
        o3d.pipelines.registration.ICPConvergenceCriteria(
            relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=iterations
        ),
    )
    refined = np.asarray(result.transformation, dtype=np.float64) if result.fitness > 0.3 else transform
    return refined, float(result.fitness)


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


@dataclasses.dataclass(frozen=True)
class OdometryStep:
    """One step of :class:`StreamOdometry`: ``ego1_from_ego0`` (4, 4) float64 from the previous scan's frame into
    this scan's (None when the track is lost: no estimate for this pair); ``fitness``: the fraction of the previous
    scan's non-ground points (down-sampled) with a point of this scan within twice the voxel after the motion;
    ``restarted``: the stream's own estimate fitted worse than ``min_fitness``, so the pair was estimated afresh from
    the two scans (a fresh KISS-ICP, as :func:`estimate_ego_motion` does) and the track starts again from it."""

    ego1_from_ego0: np.ndarray | None
    fitness: float
    restarted: bool = False


#: metres: the voxel of the stream's refinement clouds (non-ground points). Finer than the pairwise step's 0.2 m: a
#: voxel grid fixed in each scan's frame pulls a slow motion towards the identity (BENCHMARKS.md, issue 33)
STREAM_VOXEL = 0.15
#: the stream's refinement: at most this many source points (an even subsample of the previous scan's cloud) and
#: iterations (it starts from KISS-ICP's estimate, centimetres away). 2,500 rather than 4,000: 6-7 ms less per frame,
#: synthetic median 0.22 instead of 0.18 cm (BENCHMARKS.md, issue 33)
STREAM_SOURCE_POINTS, STREAM_ITERATIONS = 2500, 10
#: metres: the width of the stream refinement's robust (Tukey) kernel: the moving traffic of a fast drive pulled the
#: plain least squares by 2-3 cm (synthetic, 9.6 m/s: 2.20 -> 0.20 cm median, BENCHMARKS.md, issue 33)
STREAM_TUKEY = 0.1
#: the stream's target normals: of the nearest 10 points (6 are cheaper but tilt on a 32-beam scan's sparse rings,
#: 1.5-2 cm instead of 0.5 cm, BENCHMARKS.md, issue 33)
STREAM_NORMAL_NEIGHBOURS = 10


def local_target(points: np.ndarray, source: np.ndarray, transform: np.ndarray):
    """The open3d cloud (with normals) of the target points a refinement from ``transform`` will match: for each
    ``source`` point (K, 3) moved by ``transform``, the nearest of ``points`` (M, 3), with the normal (PCA) of the
    ``STREAM_NORMAL_NEIGHBOURS`` nearest around it (once per target point). A stream step starts centimetres from
    the answer, so its correspondences stay among these; computing normals for them alone, not for the whole scan,
    was the odometry's costliest step (BENCHMARKS.md, issue 33)."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    from icpflow.entry import signals_held

    moved = transform_points(transform, source)
    tree = cKDTree(points, balanced_tree=False, compact_nodes=False)  # built once, queried once: quicker so
    with signals_held():  # a stop inside the threaded query would free its memory under its threads
        _, neighbours = tree.query(moved, k=min(STREAM_NORMAL_NEIGHBOURS, len(points)), workers=-1)
    neighbours = neighbours.reshape(len(moved), -1)
    nearest, first = np.unique(neighbours[:, 0], return_index=True)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[nearest]))
    cloud.normals = o3d.utility.Vector3dVector(plane_normals(points[neighbours[first]]))
    return cloud


class StreamOdometry:
    """Ego motion along a stream of scans (N, 3) in one frame (the model's height frame).

    One KISS-ICP runs across the frames (its local map and constant-velocity model: the estimate a stream gets
    almost free); each step is then refined point-to-plane from it on the non-ground points of the two scans
    (``STREAM_VOXEL`` clouds; each scan is down-sampled once, is the target of its own step, with normals for the
    points that step matches (:func:`local_target`), and serves as the source of the next). The refinement's
    fitness says whether the track holds.

    :meth:`step` returns None for the first scan after a start or :meth:`reset`, else an :class:`OdometryStep`. A
    step whose fitness is below ``min_fitness`` (the track is lost: a jump, another place) is estimated afresh from
    the two scans; if that fits no better, the pair gets no estimate and the track starts again from this scan.
    ``refine=False``: KISS-ICP alone (the fitness is still measured).
    """

    def __init__(self, cfg, min_fitness: float = 0.5, refine: bool = True, voxel: float = STREAM_VOXEL):
        self.settings = ego_settings(cfg)
        self.min_fitness, self.refine, self.voxel = float(min_fitness), bool(refine), float(voxel)
        self.reset()

    def reset(self) -> None:
        """Forget the map and the motion: the next scan starts a new track."""
        self._kiss = None
        # (non-ground points, their cloud with normals, KISS pose, the cloud's subsample) of the previous scan
        self._previous = None
        self._steps = 0  # steps of this track: its first has no motion model yet (KISS-ICP starts at the identity)

    def step(self, points: np.ndarray, ground: np.ndarray | None = None) -> OdometryStep | None:
        """Register the scan ``points`` (N, 3) (``ground``: its (N,) bool ground mask, left out of the
        refinement); see the class docstring."""
        points = np.asarray(points, np.float64)
        if self._kiss is None:
            self._kiss = kiss_odometry(self.settings)
        kept = points if ground is None else points[~np.asarray(ground, bool)]
        kept = kept if len(kept) >= MIN_EGO_POINTS else points
        self._kiss.register_frame(kept, np.zeros(0))
        cloud = refinement_cloud(kept, self.voxel)
        step = max(1, len(cloud.points) // STREAM_SOURCE_POINTS)
        current = (kept, cloud, np.asarray(self._kiss.last_pose, np.float64), cloud.uniform_down_sample(step))
        previous, self._previous = self._previous, current
        if previous is None:
            return None
        self._steps += 1
        young = self._steps == 1
        transform, fitness = self._aligned(previous[3], cloud, invert(current[2]) @ previous[2], young)
        if fitness >= self.min_fitness:
            return OdometryStep(transform, fitness)
        # lost: the two scans alone (a fresh KISS-ICP, as for a single pair); the track restarts from this pair
        self._kiss = kiss_odometry(self.settings)
        self._kiss.register_frame(previous[0], np.zeros(0))
        self._kiss.register_frame(kept, np.zeros(0))
        pose = np.asarray(self._kiss.last_pose, np.float64)
        transform, fitness = self._aligned(previous[3], cloud, invert(pose), young=True)
        if fitness >= self.min_fitness:
            self._previous, self._steps = (kept, cloud, pose, current[3]), 1
            return OdometryStep(transform, fitness, restarted=True)
        self.reset()
        self.step(points, ground)  # this scan starts the new track
        return OdometryStep(None, fitness, restarted=True)

    def _aligned(self, source, target, transform: np.ndarray, young: bool = False) -> tuple[np.ndarray, float]:
        """``transform`` refined from ``source`` onto ``target`` (when ``refine``; on a ``young`` track's first step,
        whose start is KISS-ICP's estimate from one scan, as the pairwise step refines), and its fitness."""
        import open3d as o3d

        if not len(source.points) or not len(target.points):
            return transform, 0.0
        if self.refine:
            if young:  # the start may be decimetres off: plain least squares on every point, the pairwise iterations
                whole = o3d.geometry.PointCloud(target)
                whole.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(STREAM_NORMAL_NEIGHBOURS))
                return refine_clouds(source, whole, transform, self.voxel, 50)
            local = local_target(np.asarray(target.points), np.asarray(source.points), transform)
            return refine_clouds(source, local, transform, self.voxel, STREAM_ITERATIONS, STREAM_TUKEY)
        result = o3d.pipelines.registration.evaluate_registration(source, target, 2.0 * self.voxel, transform)
        return transform, float(result.fitness)
