"""Ego motion from the scans alone: one odometry for a drive, a stream and a pair (the teacher's step 1, the
Predictor, the stream and ``label.py``'s trajectory of a drive without poses).

A sequence of scans in, one ``ego1_from_ego0`` per step out: :class:`Odometry` takes each scan (N, 3) float32 in one
height frame (``icpflow.scans.preprocess``) with its (N,) bool ground mask (the ground's surface,
``icpflow.scans.ground.GroundSegmenter.masks``) and returns the transform
(4, 4) float64 from the previous scan's frame into this one's. A pair is a two-scan sequence
(:func:`estimate_ego_motion`); ``label.py`` runs one over a whole drive (``icpflow.labelling.trajectory``).

Each step: KISS-ICP (``kiss-icp`` 1.x, one instance across the track: its local map and constant-velocity model) on the
non-ground points gives a start (on every point, the ground's rings, drawn by the sensor, hold KISS-ICP near the
identity; it takes them down-sampled to one per ``VOXEL``, the cloud the refinement uses too: its own voxel grids, 0.5
and 1.5 m, keep one point per voxel anyway, so the smaller cloud registers quicker at the same or smaller errors:
BENCHMARKS.md, "Ego motion"); it is refined point-to-plane (open3d ``registration_icp``)
on ``VOXEL`` m clouds of the two whole scans (the ground's planes fix roll, pitch and height) with a robust (Tukey)
kernel that leaves moving objects out; the target's normals come from one estimate (:class:`TargetPlanes`:
``icpflow.scans.normals.plane_normals`` of a target point's ``NORMAL_NEIGHBOURS`` nearest). The first step of a track (a
pair: no motion model, a one-scan map) is refined coarse to fine and, when it fits poorly, from other starts too
(:meth:`Odometry._first_step`). A later step starts from the last step's motion instead (constant velocity,
:meth:`Odometry._velocity_step`), and KISS-ICP registers the scan only where that start, or the step from it, fits
clearly worse than the last step (a turn-around, a dropped scan); its map and motion model take the refined poses
either way. The step converges from starts up to 20 cm off, which a car at 10 Hz does not leave, and a step from the
last one's motion costs about three quarters of one that KISS-ICP registers, at about the same errors on the synthetic
drives and smaller ones on KITTI (BENCHMARKS.md, "Ego motion").

Whether the track holds: the step's fitness (the share of the previous scan's non-ground points with a point of
this scan within twice the voxel). Under ``min_fitness`` the step is estimated afresh from its two scans (a new
track); if that fits under ``LOST_FITNESS`` too (another place: 0.03-0.18 on spliced synthetic drives, where the
correct steps of the hardest drives fit 0.42-0.44), the step has no estimate (``OdometryStep.ego1_from_ego0`` None),
never a silent wrong pose.
Whether the scans fix the step: its normal spread (:func:`normal_spread`, ``OdometryStep.spread``); under
:data:`MIN_SPREAD` the step is ``unfixed`` and its callers say so in one line.

Settings: the ``ego_motion`` block (``icpflow.teacher.config.EgoMotionConfig``: KISS-ICP's voxel and range), or a
``Preprocessing`` or teacher config holding it (:func:`ego_settings`). Measured: BENCHMARKS.md, "Ego motion"
(``benchmarks/bench_ego_motion.py``).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from icpflow.core.geometry import invert, orthonormalized, transform_points
from icpflow.scans.config import EgoMotionConfig
from icpflow.scans.normals import plane_normals
from icpflow.scans.preprocess import Preprocessing

#: fewer points than this in either scan: no estimate
MIN_EGO_POINTS = 100
#: metres: the cells of a target's nearest-neighbour grid (``TargetPlanes``; its 10th neighbour lies within 0.35 m for
#: half its points: 0.5 m cells are the quickest, 0.3 m ones take 1.7x their time, 0.75 and 1 m as long or longer;
#: docs/history.md, "The odometry's neighbours from a voxel grid (point 3)")
GRID_CELL = 0.5
#: a query whose k-th neighbour lies beyond this many shells of ``GRID_CELL`` cells (a sparse, far part of a scan) is
#: answered on a second grid of ``COARSE_CELL`` m cells, exactly too: on the fine grid alone such a query visits
#: hundreds of columns or scans the whole cloud (4 % of an AV2 scan's source points take 11 of the 17 ms of its
#: normals' queries; with the coarse grid they take half the time). 3-6 shells and 1.5-2 m cells are alike, 3 m
#: cells slower (BENCHMARKS.md, "Student latency and the stream"; docs/history.md, "The odometry's normals: far
#: queries on a coarse grid (point 3)")
FINE_SHELLS, COARSE_CELL = 3, 2.0
#: metres: the voxel of the refinement clouds. Finer than KISS-ICP's: a voxel grid fixed in each scan's frame pulls a
#: slow motion towards the identity (docs/history.md, "the streaming Predictor")
VOXEL = 0.15
#: a step that fits under ``Odometry.min_fitness`` is estimated afresh from its two scans; under this after that, the
#: track is lost (module docstring)
LOST_FITNESS = 0.3
#: a step's refinement: at most this many source points (an even subsample of the previous scan's cloud) and
#: iterations (it starts from KISS-ICP's estimate, centimetres away; docs/history.md, "the streaming Predictor")
SOURCE_POINTS, ITERATIONS = 2500, 10
#: metres: the width of the refinement's robust (Tukey) kernel: the moving traffic of a fast drive pulls the plain
#: least squares by 2-3 cm (synthetic, 9.6 m/s: 2.2 cm median without the kernel, 0.2 cm with it; docs/history.md,
#: "the streaming Predictor")
TUKEY = 0.1
#: the target normals: of the nearest 10 points (6 are cheaper but tilt on a 32-beam scan's sparse rings: 1.5-2 cm
#: errors against 0.5 cm; docs/history.md, "the streaming Predictor")
NORMAL_NEIGHBOURS = 10
#: a track's later steps start from the last step's motion (constant velocity) instead of KISS-ICP's registration,
#: where that start fits at least ``VELOCITY_SHARE`` of the last step's fitness, the step from it moves it by at most
#: ``VELOCITY_REACH`` m and its share of source points within ``TIGHT`` m of a target is at least ``VELOCITY_SHARE``
#: of the last step's (else KISS-ICP registers the scan). The step converges from 20 cm off and fails from 50 cm
#: (synthetic drives; docs/history.md, "Built: a constant-velocity start for the odometry (16d8ffd)")
VELOCITY_SHARE, VELOCITY_REACH, TIGHT = 0.8, 0.2, 0.1
#: the first step of a track (a pair): at most this many source points of the whole scan (ground included: its
#: planes fix roll, pitch and height), and its (reach m, Tukey width m, iterations) stages, a wide one then a fine one
FIRST_SOURCE_POINTS = 4000
FIRST_STAGES = ((1.0, 0.3, 15), (0.3, 0.1, 30))
#: the first step's fit (the mean Tukey weight of its point-to-plane residuals, about the share of the scan that
#: fits) under which, or a result this far (m) from KISS-ICP's start, it is also refined from the identity and from
#: KISS-ICP's reverse registration, the best fit winning (docs/history.md, "One odometry")
RETRY_FIT, RETRY_JUMP = 0.45, 0.5
#: a pair's normal spread (:func:`normal_spread`) under this: the scans' surfaces leave the motion along one direction
#: unfixed (a corridor of two parallel walls; real scans lie far above it, BENCHMARKS.md "The teacher on real points")
MIN_SPREAD = 0.02
#: source points the spread is measured on (a 3 x 3 statistic: on KITTI 00 pairs within 0.02 of its value on 2,500)
SPREAD_POINTS = 300


def ego_settings(cfg) -> EgoMotionConfig:
    """The ego-motion settings of ``cfg``: an EgoMotionConfig, or a Preprocessing / teacher config holding one (a
    dict of teacher fields, older flat names included, is read by ``Preprocessing.from_teacher``)."""
    if isinstance(cfg, EgoMotionConfig):
        return cfg
    if isinstance(getattr(cfg, "ego_motion", None), EgoMotionConfig):
        return cfg.ego_motion
    return Preprocessing.from_teacher(cfg).ego_motion


def kiss_odometry(cfg, threads: int = 0):
    """A fresh ``kiss_icp.kiss_icp.KissICP`` with ``cfg``'s ego-motion settings (max range, voxel size), deskewing off
    (no per-point timestamps), its registration on ``threads`` threads (0: every core)."""
    from kiss_icp.config import load_config
    from kiss_icp.kiss_icp import KissICP

    config = load_config(None)
    config.data.deskew = False
    settings = ego_settings(cfg)
    config.data.max_range = float(settings.kiss_max_range)
    config.mapping.voxel_size = float(settings.kiss_voxel_size)
    config.registration.max_num_threads = int(threads)
    return KissICP(config)


def voxel_cloud(points: np.ndarray, voxel: float):
    """The open3d cloud of ``points`` (N, 3) down-sampled to ``voxel`` m (one measured point per voxel, KISS-ICP's
    voxel grid: 4x quicker than open3d's centroids)."""
    from kiss_icp.voxelization import voxel_down_sample

    from icpflow.core.open3d_loader import load_open3d

    o3d = load_open3d()

    kept = voxel_down_sample(np.asarray(points, np.float64), voxel)
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(kept))


class TargetPlanes:
    """A refinement's target points (M, 3) in a voxel grid (``icpflow.scans.neighbours``: exact nearest neighbours;
    a scipy k-d tree gives the same neighbours in twice the time, BENCHMARKS.md, "Student latency and the stream");
    each point's normal, one estimate: ``plane_normals`` of its ``NORMAL_NEIGHBOURS`` nearest (computed only for the
    points a source lands near: a step that starts close to the answer keeps its correspondences among these, and the
    normals of the whole scan would be the odometry's costliest step; docs/history.md, "normals only where the step
    looks"). The queries run on numba's threads."""

    def __init__(self, points: np.ndarray):
        """``points`` (M, 3)."""
        from icpflow.scans.neighbours import build_grid

        self.points = np.ascontiguousarray(points, np.float64)
        self.grid = build_grid(self.points, GRID_CELL) if len(self.points) else None
        self.coarse = None  # the points in COARSE_CELL cells, built for the first query that needs them

    def nearest(self, moved: np.ndarray, k: int, reach: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` target points nearest each of the (K, 3) ``moved`` points, closer than ``reach`` m: (distances
        (K, k) ascending, inf where there is none; indices (K, k) int64, -1 there). A query whose k-th neighbour
        lies beyond ``FINE_SHELLS`` cells is answered on the coarse grid (module constants)."""
        from icpflow.scans.neighbours import GAVE_UP, MAX_KNN_SHELL, build_grid, k_nearest

        moved = np.ascontiguousarray(moved, np.float64)
        if self.grid is None:
            return np.full((len(moved), k), np.inf), np.full((len(moved), k), -1, np.int64)
        squared, index = k_nearest(moved, self.points, self.grid, GRID_CELL, k, reach * reach, FINE_SHELLS, False)
        far = np.flatnonzero(index[:, 0] == GAVE_UP)
        if len(far):
            if self.coarse is None:
                self.coarse = build_grid(self.points, COARSE_CELL)
            squared[far], index[far] = k_nearest(
                moved[far], self.points, self.coarse, COARSE_CELL, k, reach * reach, MAX_KNN_SHELL, True
            )
        return np.where(index >= 0, np.sqrt(squared), np.inf), index

    def near(self, moved: np.ndarray | None = None):
        """For the (K, 3) ``moved`` source points (None: every target point): the open3d cloud, with normals, of the
        target points nearest to them (once each), and per source point the distance (K,) to its nearest target
        point, that point (K, 3) and its normal (K, 3)."""
        from icpflow.core.open3d_loader import load_open3d

        o3d = load_open3d()

        centres = self.points if moved is None else moved
        distance, neighbours = self.nearest(centres, min(NORMAL_NEIGHBOURS, len(self.points)))
        nearest, first, back = np.unique(neighbours[:, 0], return_index=True, return_inverse=True)
        normals = plane_normals(self.points, neighbours[first])
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points[nearest]))
        cloud.normals = o3d.utility.Vector3dVector(normals)
        return cloud, distance[:, 0], self.points[neighbours[:, 0]], normals[back]


@dataclasses.dataclass(frozen=True)
class OdometryStep:
    """One step of :class:`Odometry`: ``ego1_from_ego0`` (4, 4) float64 from the previous scan's frame into this
    scan's (None when the track is lost: no estimate for this pair); ``fitness``: the fraction of the previous scan's
    non-ground points (down-sampled) with a point of this scan within twice the voxel after the motion;
    ``restarted``: the track's own estimate fitted worse than ``min_fitness``, so the pair was estimated afresh from
    the two scans and the track starts again from it; ``spread``: :func:`normal_spread` at the estimate (None without
    the refinement)."""

    ego1_from_ego0: np.ndarray | None
    fitness: float
    restarted: bool = False
    spread: float | None = None

    @property
    def unfixed(self) -> bool:
        """The scans' surfaces leave the motion along one direction unfixed (spread under :data:`MIN_SPREAD`): the
        estimate may be wrong along it."""
        return self.spread is not None and self.spread < MIN_SPREAD

    def unfixed_warning(self) -> str:
        """The one line that says so (for a caller that found ``unfixed``)."""
        return (
            f"the scans' surfaces do not fix the ego motion along one direction (normal spread {self.spread:.3f} < "
            f"{MIN_SPREAD}: a corridor, a single wall): it may be wrong; pass the poses if they are known"
        )


@dataclasses.dataclass
class _Scan:
    ground: np.ndarray  # (G, 3) float64 ground points
    cloud: object  # the VOXEL cloud of its non-ground points (KISS-ICP's input: ``kept``)
    source: object  # its subsample, the next step's source
    kiss_pose: np.ndarray  # (4, 4) the scan's pose in its track as KISS-ICP's map holds it (refined: velocity steps)
    whole: np.ndarray | None = None  # (K, 3) the whole scan's cloud (made when needed)
    target: TargetPlanes | None = None  # the whole cloud as a refinement's target (made when needed)

    @property
    def kept(self) -> np.ndarray:
        """(M, 3) float64 the non-ground points of :attr:`cloud` (KISS-ICP's input)."""
        return np.asarray(self.cloud.points)

    def whole_cloud(self) -> np.ndarray:
        """The non-ground cloud (its first rows) with the ground's (``VOXEL`` m): what a step is refined on (the
        ground's planes fix roll, pitch and height; a coarser ground, 0.3 or 0.5 m, left 11-13 cm errors on a 32-beam
        drive)."""
        if self.whole is None:
            from kiss_icp.voxelization import voxel_down_sample

            ground = voxel_down_sample(self.ground, VOXEL) if len(self.ground) else np.zeros((0, 3))
            self.whole = np.concatenate([self.kept, ground])
        return self.whole

    def planes(self) -> TargetPlanes:
        """:meth:`whole_cloud` as a refinement's target, built once."""
        if self.target is None:
            self.target = TargetPlanes(self.whole_cloud())
        return self.target


class Odometry:
    """Ego motion along a sequence of scans (N, 3) in one frame (the height frame); see the module docstring.

    :meth:`step` returns None for the first scan after a start or :meth:`reset`, else an :class:`OdometryStep`.
    ``min_fitness``: under it a step is estimated afresh from its two scans. ``refine=False``: KISS-ICP alone (the
    fitness is still measured). ``threads``: KISS-ICP's threads (0: every core; a stream that runs its network beside
    the odometry gives it 1; None: numba's thread count where a KISS-ICP is made, i.e. the caller's limit, as a
    labelling worker's ``icpflow.core.threads.thread_limit``: each worker's KISS-ICP had taken every core); the
    nearest-neighbour queries of the refinement run on numba's threads (the caller's setting)."""

    def __init__(
        self, cfg, min_fitness: float = 0.5, refine: bool = True, voxel: float = VOXEL, threads: int | None = None
    ):
        self.settings = ego_settings(cfg)
        self.min_fitness, self.refine, self.voxel = float(min_fitness), bool(refine), float(voxel)
        self.threads = None if threads is None else int(threads)
        self.reset()

    def kiss_threads(self) -> int:
        """KISS-ICP's threads for a registration made now (class docstring)."""
        import numba

        return numba.get_num_threads() if self.threads is None else self.threads

    def reset(self) -> None:
        """Forget the map and the motion: the next scan starts a new track."""
        self._kiss = None
        self._previous: _Scan | None = None
        self._steps = 0  # steps of this track: its first has no motion model yet (KISS-ICP starts at the identity)
        self._last_match = (0.0, 0.0)  # the last step's (fitness, share within TIGHT): the velocity start's yardstick

    def step(self, points: np.ndarray, ground: np.ndarray | None = None) -> OdometryStep | None:
        """Register the scan ``points`` (N, 3) (``ground``: its (N,) bool ground mask); see the class docstring."""
        points = np.asarray(points, np.float64)
        ground = np.zeros(len(points), bool) if ground is None else np.asarray(ground, bool)
        cloud = voxel_cloud(points[~ground] if (~ground).sum() >= MIN_EGO_POINTS else points, self.voxel)
        kept = np.asarray(cloud.points)  # KISS-ICP's input (module docstring)
        if self._kiss is None:
            self._kiss = kiss_odometry(self.settings, self.kiss_threads())
        source = cloud.uniform_down_sample(max(1, len(cloud.points) // SOURCE_POINTS))
        current = _Scan(points[ground], cloud, source, np.eye(4))
        previous, self._previous = self._previous, current
        if previous is not None and self._steps >= 1 and self.refine:
            self._steps += 1
            transform = self._velocity_step(previous, current)
        else:
            self._kiss.register_frame(kept, np.zeros(0))
            current.kiss_pose = np.asarray(self._kiss.last_pose, np.float64)
            if previous is None:
                return None
            self._steps += 1
            start = invert(current.kiss_pose) @ previous.kiss_pose
            if self._steps == 1:
                transform = self._first_step(previous, current, start)
            else:
                transform = self._refined(previous, current, start)
            self._last_match = self._match(previous, current, transform)
        fitness = self._last_match[0]
        if fitness >= self.min_fitness:
            return OdometryStep(transform, fitness, spread=self._spread(previous, current, transform))
        if self._steps > 1:  # the two scans alone, a new track from this pair
            self._kiss = kiss_odometry(self.settings, self.kiss_threads())
            self._kiss.register_frame(previous.kept, np.zeros(0))
            self._kiss.register_frame(kept, np.zeros(0))
            current.kiss_pose = np.asarray(self._kiss.last_pose, np.float64)
            self._steps = 1
            transform = self._first_step(previous, current, invert(current.kiss_pose))
            self._last_match = self._match(previous, current, transform)  # the new track's yardstick
            fitness = self._last_match[0]
        if fitness >= LOST_FITNESS:
            return OdometryStep(transform, fitness, True, self._spread(previous, current, transform))
        self.reset()
        self.step(points, ground)  # this scan starts the new track
        return OdometryStep(None, fitness, restarted=True)

    def _refined(self, previous: _Scan, current: _Scan, transform: np.ndarray) -> np.ndarray:
        """``transform`` (KISS-ICP's, centimetres off) refined point-to-plane from the previous whole scan onto this
        one (``SOURCE_POINTS``, reach twice the voxel, ``TUKEY``, ``ITERATIONS``), when ``refine``."""
        if not self.refine or not len(previous.source.points) or not len(current.cloud.points):
            return transform
        source = previous.whole_cloud()
        source = source[:: max(1, len(source) // SOURCE_POINTS)]
        return _staged(source, current.planes(), transform, ((2 * self.voxel, TUKEY, ITERATIONS),))

    def _spread(self, previous: _Scan, current: _Scan, transform: np.ndarray) -> float | None:
        """:func:`normal_spread` of the previous whole scan (``SPREAD_POINTS`` of it) moved by ``transform`` onto this
        one; None without the refinement (KISS-ICP alone) or points."""
        if not self.refine or not len(previous.source.points) or not len(current.cloud.points):
            return None
        source = previous.whole_cloud()
        return normal_spread(source[:: max(1, len(source) // SPREAD_POINTS)], current.planes(), transform)

    def _match(self, previous: _Scan, current: _Scan, transform: np.ndarray) -> tuple[float, float]:
        """(fitness, tight share) of ``transform``: the fitness (module docstring) is the share of the previous
        scan's non-ground source points whose nearest point of this scan's whole cloud is a non-ground one within
        twice the voxel; the tight share, that of the same points with a point of the whole cloud within ``TIGHT`` m.
        One query gives both."""
        if not len(previous.source.points) or not len(current.cloud.points):
            return 0.0, 0.0
        moved = transform_points(transform, np.asarray(previous.source.points))
        distance, nearest = current.planes().nearest(moved, 1, 2.0 * self.voxel)
        fitness = float(np.mean((nearest[:, 0] >= 0) & (nearest[:, 0] < len(current.cloud.points))))
        return fitness, float(np.mean(distance[:, 0] <= TIGHT))

    def _velocity_step(self, previous: _Scan, current: _Scan) -> np.ndarray:
        """A later step of a track: refined from the last step's motion (KISS-ICP's constant-velocity prediction,
        its poses kept from the refined steps), or, where that start or its result fits worse than the last step
        (``VELOCITY_SHARE``, ``VELOCITY_REACH``), from KISS-ICP's registration of the scan as before. KISS-ICP's map,
        motion and threshold take the refined pose either way. Returns the step (its match in ``_last_match``)."""
        kiss = self._kiss
        frame = kiss.preprocessor.preprocess(current.kept, np.zeros(0), kiss.last_delta)
        registered, down_sampled = kiss.voxelize(frame)
        guess = kiss.last_pose @ kiss.last_delta  # world <- this scan at constant velocity
        start = invert(guess) @ previous.kiss_pose
        last_fitness, last_tight = self._last_match
        transform = None
        if self._match(previous, current, start)[0] >= VELOCITY_SHARE * last_fitness:
            refined = self._refined(previous, current, start)
            fitness, tight = self._match(previous, current, refined)
            moved = float(np.linalg.norm((invert(start) @ refined)[:3, 3]))
            if moved <= VELOCITY_REACH and tight >= VELOCITY_SHARE * last_tight:
                transform = refined
        if transform is None:  # KISS-ICP's registration, from the same prediction
            sigma = kiss.adaptive_threshold.get_threshold()
            pose = kiss.registration.align_points_to_map(
                points=registered,
                voxel_map=kiss.local_map,
                initial_guess=guess,
                max_correspondance_distance=3 * sigma,
                kernel=sigma,
            )
            transform = self._refined(previous, current, invert(pose) @ previous.kiss_pose)
            fitness, tight = self._match(previous, current, transform)
        pose = orthonormalized(previous.kiss_pose @ invert(transform))  # KISS-ICP takes rotations orthonormal to 1e-13
        kiss.adaptive_threshold.update_model_deviation(orthonormalized(invert(guess) @ pose))
        kiss.local_map.update(down_sampled, pose)
        kiss.last_delta, kiss.last_pose = orthonormalized(invert(kiss.last_pose) @ pose), pose
        current.kiss_pose = pose
        self._last_match = (fitness, tight)
        return transform

    def _first_step(self, previous: _Scan, current: _Scan, start: np.ndarray) -> np.ndarray:
        """The first step of a track, from KISS-ICP's estimate on the non-ground points of a one-scan map: refined
        point-to-plane on the whole scans through ``FIRST_STAGES`` (a wide one, then a fine one); a poor fit, or a
        result far from the start, is also refined from the identity and from KISS-ICP's reverse registration, and
        the best fit wins. Returns it (the caller measures its match, :meth:`_match`)."""
        if not self.refine or not len(previous.source.points) or not len(current.cloud.points):
            return start
        source = previous.whole_cloud()
        source = source[:: max(1, len(source) // FIRST_SOURCE_POINTS)]
        target = current.planes()
        transform = _staged(source, target, start)
        fit = _fit(source, target, transform)
        jump = float(np.linalg.norm((invert(start) @ transform)[:3, 3]))
        if fit < RETRY_FIT or jump > RETRY_JUMP:
            reverse = invert(_kiss_registration(current.kept, previous.kept, self.settings, self.kiss_threads()))
            for other in (np.eye(4), reverse):
                refined = _staged(source, target, other)
                refined_fit = _fit(source, target, refined)
                if refined_fit > fit:
                    transform, fit = refined, refined_fit
        return transform


def _staged(source: np.ndarray, target: TargetPlanes, transform: np.ndarray, stages=FIRST_STAGES) -> np.ndarray:
    """``transform`` refined point-to-plane from ``source`` (K, 3) onto ``target`` through ``stages`` ((reach m, Tukey
    width m, iterations) each), each with the normals of the target points nearest the source moved by its start."""
    from icpflow.core.open3d_loader import load_open3d

    o3d = load_open3d()
    registration = o3d.pipelines.registration
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    for reach, tukey, iterations in stages:
        result = registration.registration_icp(
            cloud,
            target.near(transform_points(transform, source))[0],
            reach,
            transform,
            registration.TransformationEstimationPointToPlane(registration.TukeyLoss(k=tukey)),
            registration.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=iterations),
        )
        transform = np.asarray(result.transformation, np.float64)
    return transform


def _fit(source: np.ndarray, target: TargetPlanes, transform: np.ndarray, width: float = TUKEY) -> float:
    """The mean Tukey weight (of ``width`` m) of the point-to-plane residuals of ``source`` (K, 3) moved by
    ``transform`` onto ``target`` (0 for a point with no target point within 0.5 m): about the share that fits."""
    moved = transform_points(transform, source)
    _, distance, nearest, normals = target.near(moved)
    residual = np.abs(np.einsum("ij,ij->i", moved - nearest, normals))
    weight = np.where((distance < 0.5) & (residual < width), (1 - (residual / width) ** 2) ** 2, 0.0)
    return float(weight.mean())


def normal_spread(source: np.ndarray, target: TargetPlanes, transform: np.ndarray) -> float:
    """The smallest eigenvalue of the mean ``n n^T`` over the target normals that ``source`` (K, 3) moved by
    ``transform`` lands on (within 0.5 m): 1/3 where the surfaces face every way, near 0 where none faces one
    direction, along which a point-to-plane fit then slides freely. 0 with fewer than 3 such points."""
    moved = transform_points(transform, source)
    _, distance, _, normals = target.near(moved)
    normals = normals[distance < 0.5]
    if len(normals) < 3:
        return 0.0
    return float(np.linalg.eigvalsh(normals.T @ normals / len(normals))[0])


def _kiss_registration(points0: np.ndarray, points1: np.ndarray, cfg, threads: int = 0) -> np.ndarray:
    """``ego1_from_ego0`` by a fresh KISS-ICP's registration (on ``threads`` threads, 0: every core) of ``points1``
    onto the map of ``points0``."""
    odometry = kiss_odometry(cfg, threads)
    odometry.register_frame(np.asarray(points0, np.float64), np.zeros(0))
    odometry.register_frame(np.asarray(points1, np.float64), np.zeros(0))
    return invert(np.asarray(odometry.last_pose, np.float64))


def estimate_ego_motion(pc0: np.ndarray, pc1: np.ndarray, cfg, ground0=None, ground1=None) -> np.ndarray | None:
    """(4, 4) float64 ``ego1_from_ego0`` of the scans (N0, 3) and (N1, 3) (their (N,) bool ground masks left out
    where given): a two-scan sequence of :class:`Odometry`. None if no estimate fits (the scans do not overlap).
    The identity, with a one-line ``UserWarning``, if either has fewer than ``MIN_EGO_POINTS`` points; where the
    scans' surfaces leave a direction unfixed (:attr:`OdometryStep.unfixed`) the estimate comes with one too."""
    if len(pc0) < MIN_EGO_POINTS or len(pc1) < MIN_EGO_POINTS:
        text = (
            f"estimate_ego_motion: a scan of {min(len(pc0), len(pc1))} points (fewer than {MIN_EGO_POINTS}) cannot "
            "be registered: the identity is assumed; pass ego1_from_ego0 if it is known"
        )
        warnings.warn_explicit(text, UserWarning, "icpflow.scans.odometry", 0)
        return np.eye(4)
    odometry = Odometry(cfg)
    odometry.step(pc0, ground0)
    step = odometry.step(pc1, ground1)
    if step.ego1_from_ego0 is None:
        return None
    if step.unfixed:
        warnings.warn_explicit(
            f"estimate_ego_motion: {step.unfixed_warning()}", UserWarning, "icpflow.scans.odometry", 0
        )
    return step.ego1_from_ego0


__all__ = [
    "MIN_EGO_POINTS",
    "Odometry",
    "OdometryStep",
    "ego_settings",
    "estimate_ego_motion",
    "kiss_odometry",
    "MIN_SPREAD",
    "normal_spread",
    "TargetPlanes",
    "voxel_cloud",
]
