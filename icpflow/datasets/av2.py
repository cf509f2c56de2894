"""Argoverse 2 sensor dataset, read from the official on-disk layout with the ``av2`` package's parts.

Layout: ``<root>/sensor/<split>/<log_id>/`` with ``sensors/lidar/<timestamp_ns>.feather`` (x, y, z float16 in the
ego frame, ...), ``city_SE3_egovehicle.feather`` (poses), ``annotations.feather`` (cuboids with track ids; absent
in the test split) and ``map/`` (``*_ground_height_surface____*.npy`` with ``*___img_Sim2_city.json``).

What a pair holds (project conventions, ``icpflow.core.frame_pair``):

* ``pc0``, ``pc1`` (N, 3) float32, each sweep in its own ego frame; ``pose0``/``pose1`` world_from_ego (the city
  frame) float64, so ``ego1_from_ego0 = inv(pose1) @ pose0`` (composed in float64; av2 composes in float32,
  which puts up to about 1e-3 m of ego-motion error into the official labels far from the city origin).
* ``time0``/``time1`` (N,) float32: each point's capture time in seconds after its sweep's timestamp, from the
  sweep's ``offset_ns`` column (0 to ~0.1 s; the two stacked lidars scan with different phases); None when a
  sweep has no ``offset_ns`` column.
* ``ground0``/``ground1``: a point is ground if it lies within ``ground_threshold`` of the map's ground height
  raster, or below it; points off the raster are not ground. The default 0.3 m is av2's own
  (``GROUND_HEIGHT_THRESHOLD_M``) and reproduces the official ``is_ground_0`` labels; 0.4 m (ZeroFlow's band)
  marks about 1.3 % more points as ground on the shipped log. The raster is read once per log and cached in the
  reader (per process, current log only; never pickled).
* With annotations: ``flow`` (N0, 3) float32 FULL flow by the rule of av2's ``Flow.from_sweep_pair`` (cuboids
  with interior points, of the same track at both timestamps, boxes grown by 0.2 m; it includes ego motion, as
  the project's convention), ``flow_valid`` (False on objects whose track ends before the second sweep),
  ``classes`` int32 = AV2 category index + 1 with 0 = none (av2's ``CATEGORY_TO_INDEX``, the convention of the
  official ``flow_labels.feather``), ``dynamic`` = residual displacement >= 0.05 m per 0.1 s of nominal gap
  (0.5 m/s), av2's rule for consecutive sweeps. No ``instance`` ids.

``pair(index, horizon=k)`` pairs sweep t with sweep t + k of the same log; samples are the sweeps t for which
t + ``max_horizon`` exists.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from icpflow.core.classes import AV2_META
from icpflow.core.frame_pair import FramePair, check_points
from icpflow.core.geometry import ego_flow, invert, transform_points
from icpflow.datasets.base import IndexedDataset, too_short
from icpflow.datasets.file_formats import fail, read_feather

POSE_COLUMNS = ("timestamp_ns", "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m")
CUBOID_COLUMNS = (
    "timestamp_ns", "track_uuid", "category", "length_m", "width_m", "height_m",
    "qw", "qx", "qy", "qz", "tx_m", "ty_m", "tz_m", "num_interior_pts",
)  # fmt: skip
LIDAR_COLUMNS = ("x", "y", "z")
#: av2's dynamic rule: residual displacement of at least 0.05 m between sweeps 0.1 s apart (0.5 m/s)
DYNAMIC_METRES_PER_SWEEP = 0.05
#: av2 grows each annotated box by this much in length and width before testing which points it contains
BOX_EXPANSION_M = 0.2


class AV2Dataset(IndexedDataset):
    """Argoverse 2 sensor-dataset sweep pairs with map ground and annotation flow (see the module docstring)."""

    name = "av2"
    class_to_meta = AV2_META

    def __init__(
        self,
        root: str | Path,
        split: str = "val",
        max_horizon: int = 1,
        ground_threshold: float = 0.3,
        with_flow: bool = True,
        logs: list[str] | None = None,
    ) -> None:
        self.root = Path(root)
        self.split = split
        self.max_horizon = int(max_horizon)
        self.ground_threshold = float(ground_threshold)
        self.with_flow = bool(with_flow)
        split_dir = self.root / "sensor" / split
        if not split_dir.is_dir():
            raise fail(split_dir, f"no such directory; expected the AV2 layout <root>/sensor/{split}/<log_id>/")
        log_dirs = sorted(p for p in split_dir.iterdir() if p.is_dir())
        if logs is not None:
            log_dirs = [d for d in log_dirs if d.name in set(logs)]
        logs = []
        for log_dir in log_dirs:
            stamps = sorted(int(p.stem) for p in (log_dir / "sensors" / "lidar").glob("*.feather") if p.stem.isdigit())
            logs.append((log_dir, stamps))
        self._index_sequences(logs)

    def why_empty(self) -> str:
        if self._index:
            return ""
        return too_short([(f"log {d.name}", len(stamps)) for d, stamps in self._sequences], self.max_horizon, "sweeps")

    def metadata(self) -> dict:
        return {**super().metadata(), "root": str(self.root), "split": self.split, "logs": len(self._sequences),
                "ground_threshold_m": self.ground_threshold}  # fmt: skip

    def pair(self, index: int, horizon: int = 1) -> FramePair:
        if not 1 <= horizon <= self.max_horizon:
            raise IndexError(f"{self.name}: horizon {horizon} outside 1..{self.max_horizon}")
        log_dir, stamps, t = self._frames(index)
        stamp0, stamp1 = stamps[t], stamps[t + horizon]
        (pc0, time0), (pc1, time1) = self._points(log_dir, stamp0), self._points(log_dir, stamp1)
        pose0, pose1 = self._pose(log_dir, stamp0), self._pose(log_dir, stamp1)
        fields = {}
        if self.with_flow and (log_dir / "annotations.feather").is_file():
            fields = self._flow(log_dir, (stamp0, stamp1), pc0, (pose0, pose1), horizon)
        return FramePair(
            pc0=pc0,
            pc1=pc1,
            pose0=pose0,
            pose1=pose1,
            ground0=self._ground(log_dir, pc0, pose0),
            ground1=self._ground(log_dir, pc1, pose1),
            time0=time0,
            time1=time1,
            dt=(stamp1 - stamp0) * 1e-9,
            log_id=log_dir.name,
            sample_id=self.sample_id(index) + ("" if horizon == 1 else f"+{horizon}"),
            timestamp0_ns=stamp0,
            timestamp1_ns=stamp1,
            source=str(self._lidar_path(log_dir, stamp0)),
            **fields,
        )

    # -- reading ---------------------------------------------------------------------------------------------
    @staticmethod
    def _lidar_path(log_dir: Path, stamp: int) -> Path:
        return log_dir / "sensors" / "lidar" / f"{stamp}.feather"

    def _points(self, log_dir: Path, stamp: int) -> tuple[np.ndarray, np.ndarray | None]:
        """(N, 3) float32 x, y, z of one sweep (ego frame) and (N,) float32 capture times (s) or None."""
        path = self._lidar_path(log_dir, stamp)
        frame = read_feather(path, LIDAR_COLUMNS, optional=("offset_ns",))
        xyz = frame[["x", "y", "z"]].to_numpy()
        if xyz.dtype == np.float16:  # AV2's own storage type: converted here, no per-sweep warning (check_points')
            xyz = xyz.astype(np.float32)
        points = check_points(xyz, path, "x, y, z", allow_empty=False)
        if "offset_ns" not in frame.columns:
            return points, None
        offsets = frame["offset_ns"].to_numpy()
        if not np.issubdtype(offsets.dtype, np.integer):
            raise fail(path, f"offset_ns must hold integer nanoseconds, got {offsets.dtype}")
        return points, (offsets * 1e-9).astype(np.float32)

    def _log_cache(self, log_dir: Path) -> dict:
        """Per-log tables and raster, kept for the current log only (samples are ordered by log)."""
        if self._cache.get("log_dir") != log_dir:
            self._cache = {"log_dir": log_dir}
        return self._cache

    def _log_table(self, log_dir: Path, filename: str, columns: tuple[str, ...]):
        cache = self._log_cache(log_dir)
        if filename not in cache:
            cache[filename] = read_feather(log_dir / filename, columns)
        return cache[filename]

    def _pose(self, log_dir: Path, stamp: int) -> np.ndarray:
        """world_from_ego (4, 4) float64 of the sweep at ``stamp``."""
        from av2.geometry.geometry import quat_to_mat

        poses = self._log_table(log_dir, "city_SE3_egovehicle.feather", POSE_COLUMNS)
        row = poses.loc[poses["timestamp_ns"].to_numpy() == stamp]
        if len(row) != 1:
            raise fail(log_dir / "city_SE3_egovehicle.feather", f"{len(row)} poses for timestamp {stamp}, need 1")
        pose = np.eye(4)
        pose[:3, :3] = quat_to_mat(row[["qw", "qx", "qy", "qz"]].to_numpy(np.float64)[0])
        pose[:3, 3] = row[["tx_m", "ty_m", "tz_m"]].to_numpy(np.float64)[0]
        return pose

    def _ground(self, log_dir: Path, points: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """(N,) bool ground mask of ego-frame ``points`` from the log's ground height raster."""
        cache = self._log_cache(log_dir)
        if "ground" not in cache:
            from av2.map.map_api import GroundHeightLayer

            try:
                cache["ground"] = GroundHeightLayer.from_file(log_dir / "map")
            except (RuntimeError, OSError, ValueError) as error:
                raise fail(log_dir / "map", f"cannot read the ground height raster: {error}") from None
        city = transform_points(pose, points.astype(np.float64))
        height = cache["ground"].get_ground_height_at_xy(city)
        with np.errstate(invalid="ignore"):
            return (np.abs(city[:, 2] - height) <= self.ground_threshold) | (city[:, 2] < height)

    def _flow(self, log_dir: Path, stamps, pc0: np.ndarray, poses, horizon: int) -> dict:
        """Full flow, validity, classes and dynamic mask of sweep 0 from the annotations.

        The rule of av2's ``Flow.from_sweep_pair`` (cuboids with interior points only, as the official labels,
        grown by 0.2 m in length and width, later cuboids overriding earlier ones, interiors by av2's ``Cuboid``),
        with each cuboid's interior test run only on the points a KD-tree puts in its bounding ball: about 10
        times faster than testing every point against every cuboid, same result.
        """
        from av2.evaluation.scene_flow.constants import CATEGORY_TO_INDEX
        from av2.structures.cuboid import CuboidList
        from scipy.spatial import cKDTree

        annotations = self._log_table(log_dir, "annotations.feather", CUBOID_COLUMNS)
        tracks = []
        for stamp in stamps:
            keep = (annotations["timestamp_ns"].to_numpy() == stamp) & (annotations["num_interior_pts"].to_numpy() > 0)
            frame = annotations.loc[keep]
            tracks.append(dict(zip(frame["track_uuid"], CuboidList.from_dataframe(frame).cuboids)))
        ego1_from_ego0 = invert(poses[1]) @ poses[0]
        rigid = ego_flow(pc0, ego1_from_ego0)
        flow = rigid.copy()
        valid = np.ones(len(pc0), bool)
        classes = np.zeros(len(pc0), np.int32)
        tree = cKDTree(pc0)
        for track, cuboid in tracks[0].items():
            cuboid.length_m += BOX_EXPANSION_M
            cuboid.width_m += BOX_EXPANSION_M
            radius = 0.5 * float(np.linalg.norm(cuboid.dims_lwh_m)) + 1e-3
            near = np.asarray(tree.query_ball_point(cuboid.xyz_center_m, radius), dtype=np.int64)
            inside = near[cuboid.compute_interior_points(pc0[near])[1]] if len(near) else near
            if str(cuboid.category) not in CATEGORY_TO_INDEX:
                raise fail(log_dir / "annotations.feather", f"unknown category {cuboid.category!r}")
            classes[inside] = CATEGORY_TO_INDEX[str(cuboid.category)]
            if track in tracks[1]:
                motion = tracks[1][track].dst_SE3_object.compose(cuboid.dst_SE3_object.inverse())
                flow[inside] = motion.transform_point_cloud(pc0[inside]).astype(np.float32) - pc0[inside]
            else:
                valid[inside] = False
        dynamic = np.linalg.norm(flow - rigid, axis=1) >= DYNAMIC_METRES_PER_SWEEP * horizon
        return {"flow": flow, "flow_valid": valid, "classes": classes, "dynamic": dynamic}
