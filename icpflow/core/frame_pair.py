"""The frame-pair schema every reader, the teacher, the shards and the student share.

A :class:`FramePair` holds two scans and whatever is known about them. Conventions (see ``icpflow.core.geometry``):

* ``pc0`` (N0, 3) float32: scan at t, ego frame of t, metres. ``pc1`` (N1, 3) float32: scan at t + dt, ego frame
  of t + dt. N0 and N1 differ in general.
* ``ego1_from_ego0`` (4, 4) float64 rigid, optional; derived from ``pose0``/``pose1`` (world_from_ego) if given.
* ``ground0`` (N0,), ``ground1`` (N1,) bool, optional.
* ``time0`` (N0,), ``time1`` (N1,) float32, optional: each point's capture time in seconds relative to its own
  scan's timestamp (``timestamp0_ns`` / ``timestamp1_ns``), e.g. Argoverse 2's ``offset_ns`` (0 to ~0.1 s across a
  spinning sweep). The points themselves stay where they were measured; the teacher can use the times to undo
  the smear of moving objects (rolling shutter). Readers without per-point times leave them None; shards do not
  store them.
* Ground truth for pc0, optional: ``flow`` (N0, 3) float32 FULL flow (``pc0 + flow`` is in the ego frame of
  t + dt), ``flow_valid`` (N0,) bool, ``classes`` (N0,) int32 (0 = background), ``instance`` (N0,) int32
  (0 = background), ``dynamic`` (N0,) bool.
* ``dt`` seconds between the scans; ids: ``log_id``, ``timestamp0_ns``, ``timestamp1_ns``, ``sample_id``.

Construction validates shapes, dtypes, finiteness and rigidity, and raises :class:`FramePairError` with a
one-line message naming ``source`` (usually the file the pair was read from). Readers convert their formats into
these dtypes at the boundary; nothing here converts silently.

A :class:`FrameSequence` holds consecutive scans with poses and, optionally, per-instance object poses, and
produces the pair (t, t + k) with exact ground truth for any gap k (the long-horizon view).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field, fields, replace

import numpy as np

from icpflow.core.geometry import (
    ego_flow,
    full_to_residual,
    invert,
    relative_transform,
    rigid_problem,
    transform_points,
)

#: the console prints a logger's last name: its lines say ``frames:`` (what they are about), not the module's name
log = logging.getLogger("icpflow.core.frames")


class FramePairError(ValueError):
    """A frame pair (or the file it came from) breaks the schema. The message is one line."""


#: an array with more columns than this, and more columns than rows, is a transposed scan ((3, N) or (4, N))
MAX_POINT_COLUMNS = 8
#: the most points a scan (or a shard's cloud) may hold, checked by every reader against what a file claims before
#: anything is allocated: about 25 times the densest scans of the field (64-beam sweeps of 1-2e5 points); a small
#: file can claim far more (a 233 KB .npz of zeros claims 2e7 points, 4.8 GB). A sensor of denser scans sets the
#: environment variable ICPFLOW_MAX_POINTS (read when the package is imported).
MAX_POINTS = int(os.environ.get("ICPFLOW_MAX_POINTS", 5_000_000))
#: the most values of one array a reader allocates (a scan of ``MAX_POINTS`` rows of 16 values)
MAX_ARRAY_VALUES = 16 * MAX_POINTS


def check_points(
    values, source, name: str = "points", *, schema: bool = False, finite: bool = True, allow_empty: bool = True
) -> np.ndarray:
    """The one check of point clouds wherever they enter: the scan readers, the frame-pair schema, the inference
    CLI, the Predictor and the teacher's API. Raises :class:`FramePairError` (one line naming ``source`` and
    ``name``) unless ``values`` is a numeric (N, >= 3) array whose rows are points.

    A transposed array ((3, N), (4, N): more than ``MAX_POINT_COLUMNS`` columns and more columns than rows) is an
    error, not N = 3 points. ``finite``: rows with NaN or Inf are an error giving their count (the teacher, which
    drops and counts them itself, passes False). ``allow_empty``: whether N = 0 is fine. Returns the first three
    columns as a C-contiguous, writeable (N, 3) float32 array (integer or float16 coordinates are converted with
    a logged warning: integers are whole metres). ``schema``: the frame-pair schema's rule, nothing converted: a
    float32 (N, 3) numpy array, returned as it is.
    """
    if schema and not isinstance(values, np.ndarray):
        raise FramePairError(f"{source}: {name} must be a numpy array, got {type(values).__name__}")
    array = np.asarray(values)
    numeric = np.issubdtype(array.dtype, np.number) and not np.issubdtype(array.dtype, np.complexfloating)
    if array.ndim == 2 and array.shape[1] > MAX_POINT_COLUMNS and array.shape[1] > array.shape[0]:
        raise FramePairError(
            f"{source}: {name} has shape {array.shape}: a transposed scan? points must be the rows "
            f"of an (N, 3) array (x, y, z first); transpose it"
        )
    if schema and (array.ndim != 2 or array.shape[1] != 3):
        raise FramePairError(f"{source}: {name} must have shape (N, 3), got {array.shape}")
    if array.ndim != 2 or array.shape[1] < 3 or not numeric:
        raise FramePairError(f"{source}: {name} must be a numeric (N, 3) array, got {array.dtype} {array.shape}")
    rows = len(array)
    if rows > MAX_POINTS:
        raise FramePairError(
            f"{source}: {name} holds {rows} points, over the cap of {MAX_POINTS} (icpflow.core.frame_pair)"
        )
    if schema and array.dtype != np.float32:
        raise FramePairError(f"{source}: {name} must be float32, got {array.dtype}")
    if not allow_empty and rows == 0:
        raise FramePairError(f"{source}: {name} is an empty scan")
    points = array if schema else np.require(array[:, :3], np.float32, ["C", "W"])
    if finite and not np.isfinite(points).all():  # the rows counted only where one fails (a slow reduction)
        bad = int((~np.isfinite(points)).any(axis=1).sum())
        raise FramePairError(f"{source}: {name} has {bad} rows with NaN or Inf (of {rows})")
    if not schema and array.dtype.kind in "iu":
        log.warning("%s: %s has %s coordinates, read as metres: whole metres only", source, name, array.dtype)
    elif not schema and array.dtype == np.float16:
        log.warning("%s: %s has float16 coordinates (3 significant digits), read as float32", source, name)
    return points


def _check_per_point(name: str, value, count: int, kind: str, source: str, width: int | None = None) -> np.ndarray:
    if value is None:
        return None
    if not isinstance(value, np.ndarray):
        raise FramePairError(f"{source}: {name} must be a numpy array, got {type(value).__name__}")
    shape = (count,) if width is None else (count, width)
    if value.shape != shape:
        raise FramePairError(f"{source}: {name} must have shape {shape}, got {value.shape}")
    if kind == "bool" and value.dtype != np.bool_:
        raise FramePairError(f"{source}: {name} must be bool, got {value.dtype}")
    if kind == "int32" and value.dtype != np.int32:
        raise FramePairError(f"{source}: {name} must be int32, got {value.dtype}")
    if kind == "float32":
        if value.dtype != np.float32:
            raise FramePairError(f"{source}: {name} must be float32, got {value.dtype}")
        if not np.all(np.isfinite(value)):
            raise FramePairError(f"{source}: {name} has NaN or Inf values")
    return value


def _check_transform(name: str, value, source: str) -> np.ndarray | None:
    if value is None:
        return None
    value = np.asarray(value)
    if value.dtype != np.float64:
        raise FramePairError(f"{source}: {name} must be float64, got {value.dtype}")
    problem = rigid_problem(value)
    if problem:
        raise FramePairError(f"{source}: {name} {problem}")
    return value


@dataclass
class FramePair:
    """Two consecutive LiDAR scans in the project's schema (see the module docstring for frames and dtypes)."""

    pc0: np.ndarray
    pc1: np.ndarray
    ego1_from_ego0: np.ndarray | None = None
    pose0: np.ndarray | None = None
    pose1: np.ndarray | None = None
    ground0: np.ndarray | None = None
    ground1: np.ndarray | None = None
    time0: np.ndarray | None = None
    time1: np.ndarray | None = None
    flow: np.ndarray | None = None
    flow_valid: np.ndarray | None = None
    classes: np.ndarray | None = None
    instance: np.ndarray | None = None
    dynamic: np.ndarray | None = None
    dt: float = 0.1
    log_id: str = ""
    sample_id: str = ""
    timestamp0_ns: int | None = None
    timestamp1_ns: int | None = None
    source: str = field(default="<memory>", compare=False)

    def __post_init__(self) -> None:
        src = self.source
        check_points(self.pc0, src, "pc0", schema=True)
        check_points(self.pc1, src, "pc1", schema=True)
        n0, n1 = len(self.pc0), len(self.pc1)
        self.pose0 = _check_transform("pose0", self.pose0, src)
        self.pose1 = _check_transform("pose1", self.pose1, src)
        self.ego1_from_ego0 = _check_transform("ego1_from_ego0", self.ego1_from_ego0, src)
        if (self.pose0 is None) != (self.pose1 is None):
            raise FramePairError(f"{src}: pose0 and pose1 must be given together")
        if self.pose0 is not None:
            derived = relative_transform(self.pose0, self.pose1)
            if self.ego1_from_ego0 is None:
                self.ego1_from_ego0 = derived
            elif not np.allclose(derived, self.ego1_from_ego0, atol=1e-3):
                raise FramePairError(f"{src}: ego1_from_ego0 disagrees with inv(pose1) @ pose0")
        _check_per_point("ground0", self.ground0, n0, "bool", src)
        _check_per_point("ground1", self.ground1, n1, "bool", src)
        _check_per_point("time0", self.time0, n0, "float32", src)
        _check_per_point("time1", self.time1, n1, "float32", src)
        _check_per_point("flow", self.flow, n0, "float32", src, width=3)
        _check_per_point("flow_valid", self.flow_valid, n0, "bool", src)
        _check_per_point("classes", self.classes, n0, "int32", src)
        _check_per_point("instance", self.instance, n0, "int32", src)
        _check_per_point("dynamic", self.dynamic, n0, "bool", src)
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise FramePairError(f"{src}: dt must be a positive number of seconds, got {self.dt}")

    @property
    def has_ground_truth(self) -> bool:
        return self.flow is not None

    def ego_flow(self) -> np.ndarray:
        """(N0, 3) float32 full flow pc0 would have if everything were static. Needs ``ego1_from_ego0``."""
        return ego_flow(self.pc0, self._require_ego())

    def residual_flow(self) -> np.ndarray:
        """(N0, 3) float32 ground-truth ego-compensated flow. Needs ``flow`` and ``ego1_from_ego0``."""
        if self.flow is None:
            raise FramePairError(f"{self.source}: pair has no ground-truth flow")
        return full_to_residual(self.flow, self.pc0, self._require_ego())

    def pc0_in_frame1(self) -> np.ndarray:
        """(N0, 3) float32 pc0 moved into the ego frame of t + dt by the ego motion (ego compensation)."""
        return transform_points(self._require_ego(), self.pc0)

    def replace(self, **changes) -> FramePair:
        """A validated copy with some fields replaced."""
        return replace(self, **changes)

    def arrays(self) -> dict[str, np.ndarray]:
        """The array fields that are set, by name."""
        return {f.name: getattr(self, f.name) for f in fields(self) if isinstance(getattr(self, f.name), np.ndarray)}

    def _require_ego(self) -> np.ndarray:
        if self.ego1_from_ego0 is None:
            raise FramePairError(f"{self.source}: pair has no ego1_from_ego0 (nor poses)")
        return self.ego1_from_ego0


@dataclass
class FrameSequence:
    """Consecutive scans of one log with exact rigid ground truth, giving the pair (t, t + k) for any k.

    * ``points[t]`` (N_t, 3) float32 in the ego frame of scan t; ``poses`` (T, 4, 4) float64 world_from_ego.
    * optional per-scan ``ground[t]`` bool, ``classes[t]`` int32, ``instance[t]`` int32 (0 = background).
    * ``object_poses`` maps an instance id to (T, 4, 4) float64 world_from_object per scan: every point of that
      instance moves rigidly with it. Background points (instance 0, or ids without poses) are static in the world.
    * ``timestamps_ns`` (T,) int64.
    """

    points: list[np.ndarray]
    poses: np.ndarray
    timestamps_ns: np.ndarray
    ground: list[np.ndarray] | None = None
    classes: list[np.ndarray] | None = None
    instance: list[np.ndarray] | None = None
    object_poses: dict[int, np.ndarray] = field(default_factory=dict)
    dynamic_speed: float = 0.5
    log_id: str = ""
    source: str = field(default="<memory>", compare=False)

    def __post_init__(self) -> None:
        count = len(self.points)
        if np.shape(self.poses) != (count, 4, 4) or len(self.timestamps_ns) != count:
            raise FramePairError(
                f"{self.source}: {count} scans need poses (T, 4, 4) and T timestamps, got "
                f"{np.shape(self.poses)} and {len(self.timestamps_ns)}"
            )
        for t, pts in enumerate(self.points):
            check_points(pts, self.source, f"points[{t}]", schema=True)
        for name, kind in (("ground", "bool"), ("classes", "int32"), ("instance", "int32")):
            values = getattr(self, name)
            if values is not None:
                for t, value in enumerate(values):
                    _check_per_point(f"{name}[{t}]", value, len(self.points[t]), kind, self.source)
        for t, pose in enumerate(self.poses):
            _check_transform(f"poses[{t}]", np.asarray(pose), self.source)

    def __len__(self) -> int:
        return len(self.points)

    def pair(self, t: int, k: int = 1) -> FramePair:
        """The pair (scan t, scan t + k) with exact full flow for scan t's points."""
        if not (0 <= t and t + k < len(self) and k >= 1):
            raise IndexError(f"{self.source}: pair ({t}, {t + k}) outside a sequence of {len(self)} scans")
        pc0 = self.points[t]
        flow = None
        dynamic = None
        if self.instance is not None:
            ego1_from_world = invert(self.poses[t + k])
            world = transform_points(self.poses[t], pc0.astype(np.float64))
            instance = self.instance[t]
            moved = world.copy()
            order = np.argsort(instance, kind="stable")  # each instance's rows, found in one pass
            ids, starts = np.unique(instance[order], return_index=True)
            for inst, rows in zip(ids, np.split(order, starts[1:])):
                if inst == 0 or int(inst) not in self.object_poses:
                    continue
                obj = self.object_poses[int(inst)]
                moved[rows] = transform_points(obj[t + k] @ invert(obj[t]), world[rows])
            at_t1 = transform_points(ego1_from_world, moved)
            flow = (at_t1 - pc0.astype(np.float64)).astype(np.float32)
            dt = (self.timestamps_ns[t + k] - self.timestamps_ns[t]) * 1e-9
            speed = np.linalg.norm((moved - world), axis=1) / dt
            dynamic = speed > self.dynamic_speed
        pick = lambda values, i: None if values is None else values[i]  # noqa: E731
        return FramePair(
            pc0=pc0,
            pc1=self.points[t + k],
            pose0=np.asarray(self.poses[t], np.float64),
            pose1=np.asarray(self.poses[t + k], np.float64),
            ground0=pick(self.ground, t),
            ground1=pick(self.ground, t + k),
            flow=flow,
            classes=pick(self.classes, t),
            instance=pick(self.instance, t),
            dynamic=dynamic,
            dt=float((self.timestamps_ns[t + k] - self.timestamps_ns[t]) * 1e-9),
            log_id=self.log_id,
            sample_id=f"{self.log_id}/{t:06d}+{k}",
            timestamp0_ns=int(self.timestamps_ns[t]),
            timestamp1_ns=int(self.timestamps_ns[t + k]),
            source=self.source,
        )
