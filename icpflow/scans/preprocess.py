"""The preprocessing a student needs before its network: the height frame, ground removal and ego motion.

One typed block, :class:`Preprocessing`, written once into shards (``preprocessing`` in the labeller YAML),
checkpoints (``data.preprocessing`` of the saved config) and export metadata (``preprocessing``), and read back by
:meth:`Preprocessing.from_dict`, which also reads the older forms (a dict of ``ICPFlowConfig`` fields: shards,
checkpoints and exports written before this block existed).

The height frame (README, "Conventions"): the network and the teacher see points in the ego frame, x forward, y
left, z up, with the origin on (or within half a metre of) the ground below the sensor, so the ground lies near
z = 0: the synthetic world (ground at 0), Argoverse 2 (ego origin at the rear axle, ground near -0.32 m) and
KITTI as its reader delivers it (the velodyne frame lifted by the 1.73 m mounting height). :class:`HeightFrame`
records where the ground sits in the frame a model was trained in (``ground_z``); a scan in another frame (a
sensor frame, ground ``sensor_height`` below the origin) is lifted by :func:`lift_points` /
:func:`lift_transform` at the boundary. :func:`estimate_ground_height` finds the ground below the sensor of a raw
scan (a robust plane fit through the lowest point of each 2 m cell), for sensors of unknown mounting height.

Shapes: points (N, 3) float32 metres; transforms (4, 4) float64 ``b_from_a``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from icpflow.core.errors_and_signals import one_line
from icpflow.scans.config import EgoMotionConfig, GroundConfig

VERSION = 1
#: metres of the sensor above the ground in ``Preprocessing()``'s height frame: the synthetic world's LiDAR
#: (``icpflow.datasets.synthetic.lidar.SENSOR_HEIGHT``)
DEFAULT_SENSOR_HEIGHT = 1.9
FRAME_DESCRIPTION = (
    "ego frame, metres, x forward, y left, z up, origin on or near the ground below the sensor: the ground lies "
    "near z = ground_z (0 for the synthetic world and KITTI as read, -0.32 for Argoverse 2's rear-axle origin)"
)
#: A scan whose ground is further than this from a model's ``ground_z`` (m) is in another frame.
FRAME_TOLERANCE = 0.5
#: Plausibility of the preprocessing of one scan (Predictor, fastflow3d-infer): more ground than this, or fewer of
#: the points inside the network's grid, and the result is suspect (a wrong frame or settings; warned in one line).
#: Not 60 %: SemanticKITTI labels 68 % of the points of sequence 01 (a highway through fields) as ground, and the
#: synthetic settings in the right frame call 78.5 % ground there, against 91.8 % in the wrong (velodyne) frame.
MAX_GROUND_FRACTION = 0.85
MIN_GRID_FRACTION = 0.2


class PreprocessingError(ValueError):
    """A preprocessing block that cannot be read (message: one line, naming the field)."""


def _number(name: str, value, minimum: float | None = None, strict: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value:
        raise PreprocessingError(f"{name}={value!r} must be a number")
    if minimum is not None and (value <= minimum if strict else value < minimum):
        raise PreprocessingError(f"{name}={value!r} must be {'>' if strict else '>='} {minimum}")
    return float(value)


@dataclass(frozen=True)
class HeightFrame:
    """Where the ground sits (``ground_z``, m) in the frame the network sees (module docstring)."""

    ground_z: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "ground_z", round(_number("frame.ground_z", self.ground_z), 6) + 0.0)  # no -0.0


#: the ground method of every stored form older than the ``local`` method that does not name one
LEGACY_GROUND_METHOD = "both"
#: older flat teacher names (``ICPFlowConfig`` before its ``ground`` and ``ego_motion`` blocks, as stored in the
#: shards, checkpoints and exports of older releases) -> (block, field); read from the fields' ``old``
TEACHER_NAMES = {
    f.metadata.get("old") or f.name: (block, f.name)
    for block, kind in (("ground", GroundConfig), ("ego_motion", EgoMotionConfig))
    for f in dataclasses.fields(kind)
}
#: the teacher's blocks that are this block's
BLOCKS = {"ground": GroundConfig, "ego_motion": EgoMotionConfig}


def _block_values(teacher, block: str) -> dict:
    """The fields of ``block`` in ``teacher``: an ``ICPFlowConfig`` (its block), or a dict in the nested form (the
    block as a dict) or the older flat one (``sensor_height``, ``ground_slack``, ...); None values are left out."""
    if not isinstance(teacher, dict):
        value = getattr(teacher, block, None)
        return {} if value is None else dataclasses.asdict(value)
    nested = teacher.get(block)
    values = dict(nested) if isinstance(nested, dict) else {}
    for name, (owner, key) in TEACHER_NAMES.items():
        if owner == block and not (name == block and isinstance(nested, dict)) and teacher.get(name) is not None:
            values[key] = teacher[name]
    return {key: value for key, value in values.items() if value is not None}


def _settings(kind, values: dict, where: str):
    try:
        return kind(**values)
    except TypeError as error:
        raise PreprocessingError(f"{where}: {one_line(error)}") from None
    except ValueError as error:
        raise PreprocessingError(str(error)) from None


@dataclass(frozen=True)
class Preprocessing:
    """The height frame, ground settings and ego-motion settings of a teacher, as a student needs them at inference.
    ``ground`` and ``ego_motion`` are the teacher's own blocks (``icpflow.teacher.config``); ``ground``'s
    ``patchwork_z_offset`` follows from the frame (``-(sensor_height + frame.ground_z)``, set here).
    ``Preprocessing()`` is the synthetic world's (ground at z = 0, its sensor ``DEFAULT_SENSOR_HEIGHT`` above)."""

    frame: HeightFrame = field(default_factory=HeightFrame)
    ground: GroundConfig = field(default_factory=lambda: GroundConfig(sensor_height=DEFAULT_SENSOR_HEIGHT))
    ego_motion: EgoMotionConfig = field(default_factory=EgoMotionConfig)

    def __post_init__(self):
        offset = round(-(self.ground.sensor_height + self.frame.ground_z), 6) + 0.0
        if self.ground.patchwork_z_offset != offset:
            object.__setattr__(self, "ground", dataclasses.replace(self.ground, patchwork_z_offset=offset))

    @property
    def patchwork_z_offset(self) -> float:
        """Added to z before Patchwork++, so that the frame's ground sits at -sensor_height."""
        return self.ground.patchwork_z_offset

    # ------------------------------------------------------------------------------------ the teacher's config
    @classmethod
    def from_teacher(cls, teacher) -> Preprocessing:
        """The block of a teacher config: an ``ICPFlowConfig``, or a dict of its fields (nested, or the older flat
        names of shards, checkpoints and exports written before the ``ground`` / ``ego_motion`` blocks)."""
        ground = _settings(GroundConfig, _block_values(teacher, "ground"), "ground")
        ego_motion = _settings(EgoMotionConfig, _block_values(teacher, "ego_motion"), "ego_motion")
        return cls(HeightFrame(-(ground.sensor_height + ground.patchwork_z_offset)), ground, ego_motion)

    def teacher_fields(self) -> dict:
        """The same settings as ``ICPFlowConfig`` blocks (to build or override a teacher config)."""
        return {"ground": dataclasses.asdict(self.ground), "ego_motion": dataclasses.asdict(self.ego_motion)}

    # ------------------------------------------------------------------------------------ stored form
    def to_dict(self) -> dict:
        """Plain dict (JSON / YAML) with ``version``, ``frame``, ``ground``, ``ego_motion`` (``ground`` without its
        ``patchwork_z_offset``: the frame says it)."""
        values = dataclasses.asdict(self)
        del values["ground"]["patchwork_z_offset"]
        return {"version": VERSION, "frame_description": FRAME_DESCRIPTION, **values}

    @classmethod
    def from_dict(cls, values: dict | None) -> Preprocessing:
        """Read :meth:`to_dict`'s form, or an older one: a dict of ``ICPFlowConfig`` fields (shards, checkpoints and
        exports written before this block; their frame follows from the fields: ground at 0 for the synthetic
        world, -0.32 for AV2), or None (an export without teacher settings: ``ICPFlowConfig()``'s fields, ground
        at z = 0 where it was trained, the synthetic world). A stored form older than the ``local`` ground method
        that names none keeps the ground of its time (``LEGACY_GROUND_METHOD``)."""
        if values is None:
            legacy = cls.from_teacher({"ground": LEGACY_GROUND_METHOD})
            return dataclasses.replace(legacy, frame=HeightFrame(0.0))
        if not isinstance(values, dict):
            raise PreprocessingError(f"preprocessing must be a mapping, got {type(values).__name__}")
        if "version" not in values:
            nested = values.get("ground")
            if not (isinstance(nested, str) or (isinstance(nested, dict) and "method" in nested)):
                values = {**values, "ground": {**(nested or {}), "method": LEGACY_GROUND_METHOD}}
            return cls.from_teacher(values)
        if values["version"] != VERSION:
            raise PreprocessingError(
                f"preprocessing version {values['version']!r} is newer than this code's ({VERSION}); update icpflow"
            )
        try:
            frame = HeightFrame(**values.get("frame", {}))
        except TypeError as error:
            raise PreprocessingError(f"preprocessing: {one_line(error)}") from None
        ground = {key: value for key, value in values.get("ground", {}).items() if key != "patchwork_z_offset"}
        ground = _settings(GroundConfig, ground, "preprocessing")
        ego_motion = _settings(EgoMotionConfig, values.get("ego_motion", {}), "preprocessing")
        return cls(frame, ground, ego_motion)


# ------------------------------------------------------------------------------------------------ the height frame


def lift_points(points: np.ndarray, lift: float) -> np.ndarray:
    """(N, 3) float32 points moved up by ``lift`` metres (a new array; the same array when lift is 0)."""
    if lift == 0:
        return points
    lifted = np.array(points, dtype=np.float32, copy=True)
    lifted[:, 2] += np.float32(lift)
    return lifted


def lift_transform(transform: np.ndarray, lift: float) -> np.ndarray:
    """A (4, 4) ``b_from_a`` between two frames that are both raised by ``lift`` m: ``L @ T @ inv(L)``, L the
    translation (0, 0, lift). Poses ``world_from_sensor`` become ``world_from_lifted`` by ``T @ inv(L)``."""
    raise_by = np.eye(4)
    raise_by[2, 3] = lift
    lower = np.eye(4)
    lower[2, 3] = -lift
    return raise_by @ np.asarray(transform, np.float64) @ lower


def lift_pose(pose: np.ndarray, lift: float) -> np.ndarray:
    """(4, 4) ``world_from_sensor`` -> ``world_from_lifted`` for a frame raised by ``lift`` m above the sensor's."""
    lower = np.eye(4)
    lower[2, 3] = -lift
    return np.asarray(pose, np.float64) @ lower


def estimate_ground_height(
    points: np.ndarray, cell: float = 2.0, min_range: float = 2.0, max_range: float = 30.0
) -> float | None:
    """z (m) of the ground below the origin of a raw (N, 3) scan, or None when too few points to tell.

    The lowest point of each ``cell`` x ``cell`` m column between ``min_range`` and ``max_range`` m from the
    origin (horizontally) is a ground candidate; a plane z = a x + b y + c is fitted to the candidates within
    0.25 m of it, starting from their median and refitted three times, and c is returned. Walls, cars and
    vegetation raise a column's lowest point only where they hide all the ground, so the fit follows the road;
    for a level sensor h m above a flat road, the result is -h.
    """
    points = np.asarray(points)
    radius = np.hypot(points[:, 0], points[:, 1])
    near = points[(radius > min_range) & (radius < max_range)].astype(np.float64)
    if len(near) < 100:
        return None
    cells = np.floor(near[:, :2] / cell).astype(np.int64)
    key = (cells[:, 0] - cells[:, 0].min()) * (cells[:, 1].max() - cells[:, 1].min() + 1) + cells[:, 1]
    order = np.lexsort((near[:, 2], key))
    _, first = np.unique(key[order], return_index=True)
    lowest = near[order[first]]
    if len(lowest) < 10:
        return None
    design = np.c_[lowest[:, :2], np.ones(len(lowest))]
    plane = np.array([0.0, 0.0, np.median(lowest[:, 2])])
    for _ in range(4):
        inliers = np.abs(design @ plane - lowest[:, 2]) < 0.25
        if inliers.sum() < 10:
            break
        plane = np.linalg.lstsq(design[inliers], lowest[inliers, 2], rcond=None)[0]
    return float(plane[2])


def implausible(ground_fraction: float, grid_fraction: float) -> str | None:
    """A one-line reason when a scan's preprocessing looks wrong (module constants), else None."""
    problems = []
    if ground_fraction > MAX_GROUND_FRACTION:
        problems.append(f"{ground_fraction:.0%} of the points called ground (> {MAX_GROUND_FRACTION:.0%})")
    if grid_fraction < MIN_GRID_FRACTION:
        problems.append(f"{grid_fraction:.0%} of the points inside the network's grid (< {MIN_GRID_FRACTION:.0%})")
    return "; ".join(problems) or None


__all__ = [
    "HeightFrame",
    "Preprocessing",
    "PreprocessingError",
    "estimate_ground_height",
    "implausible",
    "lift_points",
    "lift_pose",
    "lift_transform",
]
