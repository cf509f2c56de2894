"""Your own LiDAR recording: an ordered directory of scans, consecutive scans becoming pairs.

Files: ``<root>/*.bin`` (float32 rows x, y, z, reflectance, the KITTI layout; another layout needs
``bin_columns``, the number of float32 values per row, x, y, z first), ``*.npy`` ((N, >= 3) array), or
``*.ply`` / ``*.pcd`` (read by open3d), in natural name order (``2.bin`` before ``10.bin``); one format per
folder. Optional poses: ``poses_file`` (relative to ``root`` or absolute), default ``<root>/poses.txt`` when it
exists: one pose per scan, world_from_sensor, as 12 values a line (row-major 3 x 4, KITTI) or 16 (4 x 4), or a
``.npy`` of shape (T, 4, 4).

What a pair holds: ``pc0``/``pc1`` (N, 3) float32 in the project's height frame (``icpflow.scans.preprocess``: origin on
the ground below the sensor, ground near z = 0): every scan is lifted by ``sensor_height`` m, a number (the
sensor's height above the ground; 0 for scans already in such an ego frame) or ``auto`` (estimated once per
folder from the first scan by ``icpflow.scans.preprocess.estimate_ground_height``, whatever the mounting height; a
ground found within 0.5 m of z = 0 means the scans are in the height frame already and stay as they are); with
poses, ``pose0``/``pose1`` (lowered onto that origin) and hence ``ego1_from_ego0``; without, None (the teacher
estimates the pair's ego motion, ``icpflow.scans.odometry``), unless the drive's trajectory was handed over
(:meth:`ScanSequenceDataset.use_ego_motions`: ``label.py`` estimates it once, in order, before labelling; a pair
across a lost track then fails with that reason). No ground truth. ``dt`` = horizon / ``frequency_hz``. Samples
are the scans t for which t + ``max_horizon`` exists.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from icpflow.core.frame_pair import FramePair, FramePairError
from icpflow.datasets.base import PairDataset
from icpflow.datasets.file_formats import SCAN_SUFFIXES, fail, list_scans, read_poses, read_scan
from icpflow.scans.preprocess import FRAME_TOLERANCE, estimate_ground_height, lift_points, lift_pose


class ScanSequenceDataset(PairDataset):
    """Consecutive scans of one directory as frame pairs (see the module docstring)."""

    name = "sequence"

    def __init__(
        self,
        root: str | Path,
        poses_file: str | Path | None = None,
        frequency_hz: float = 10.0,
        max_horizon: int = 1,
        bin_columns: int | None = None,
        sensor_height: float | str = "auto",
    ) -> None:
        self.root = Path(root)
        if not (sensor_height == "auto" or (isinstance(sensor_height, (int, float)) and sensor_height >= 0)):
            raise ValueError(f"sequence: sensor_height={sensor_height!r} must be 'auto' or metres >= 0")
        self.sensor_height = sensor_height
        self.bin_columns = bin_columns
        self.frequency_hz = float(frequency_hz)
        self.max_horizon = int(max_horizon)
        if not self.root.is_dir():
            raise fail(self.root, "not a folder of scans")
        self.scans = list_scans(self.root, one_format=True)
        if not self.scans:
            raise fail(self.root, f"need scans of one format ({', '.join(SCAN_SUFFIXES)}), found none")
        if len(self.scans) <= self.max_horizon:
            raise fail(self.root, f"{len(self.scans)} scans make no pair at horizon {self.max_horizon}")
        if poses_file is None and (self.root / "poses.txt").is_file():
            poses_file = "poses.txt"
        self.poses_file = None if poses_file is None else self.root / poses_file
        self._poses: np.ndarray | None = None
        self.poses()  # read and checked now: a broken poses file stops a run before any work, not every sample
        self._lift: float | None = None
        self._motions: np.ndarray | None = None  # the drive's ego motion, scan i to i + 1 (use_ego_motions)

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_poses": None}

    def lift(self) -> float:
        """Metres every scan is raised by (module docstring); ``auto``: minus the ground height found below the
        sensor in the first scan (0 where it finds none or finds it within 0.5 m of z = 0: scans already in the
        height frame are left as they are)."""
        if self._lift is None:
            if self.sensor_height == "auto":
                ground = estimate_ground_height(read_scan(self.scans[0], self.bin_columns))
                near = ground is None or abs(ground) <= FRAME_TOLERANCE  # already in the height frame
                self._lift = 0.0 if near else -ground
            else:
                self._lift = float(self.sensor_height)
        return self._lift

    def __len__(self) -> int:
        return len(self.scans) - self.max_horizon

    def sample_id(self, index: int) -> str:
        return self.scans[index].stem

    def metadata(self) -> dict:
        return {**super().metadata(), "root": str(self.root),
                "poses_file": None if self.poses_file is None else str(self.poses_file),
                "sensor_height": self.sensor_height}  # fmt: skip

    def poses(self) -> np.ndarray | None:
        """(T, 4, 4) float64 world_from_sensor poses, one per scan, or None without a poses file."""
        if self.poses_file is not None and self._poses is None:
            poses = read_poses(self.poses_file)
            if len(poses) != len(self.scans):
                raise fail(self.poses_file, f"{len(poses)} poses for {len(self.scans)} scans in {self.root}")
            self._poses = poses
        return self._poses

    def scan(self, index: int) -> np.ndarray:
        """Scan ``index`` (N, 3) float32 in the height frame."""
        return lift_points(read_scan(self.scans[index], self.bin_columns), self.lift())

    def drive_without_poses(self):
        if self.poses() is not None:
            return None
        return list(self.scans), self.scan

    def use_ego_motions(self, motions) -> None:
        motions = np.asarray(motions, np.float64)
        if motions.shape != (len(self.scans) - 1, 4, 4):
            raise ValueError(f"{self.root}: {len(self.scans)} scans need ({len(self.scans) - 1}, 4, 4) ego motions")
        self._motions = motions

    def _drive_motion(self, index: int, horizon: int) -> np.ndarray | None:
        """``ego{t+k}_from_ego{t}`` from the drive's ego motion, None without one; raises when a step is missing."""
        if self._motions is None:
            return None
        motion = np.eye(4)
        for step in range(index, index + horizon):
            if not np.isfinite(self._motions[step]).all():
                raise FramePairError(
                    f"{self.scans[step + 1]}: no ego motion from {self.scans[step].name} (the drive's odometry "
                    "lost track, or a scan was unreadable or too small to register; see the labelling's warnings)"
                )
            motion = self._motions[step] @ motion
        return motion

    def pair(self, index: int, horizon: int = 1) -> FramePair:
        if not 1 <= horizon <= self.max_horizon:
            raise IndexError(f"{self.name}: horizon {horizon} outside 1..{self.max_horizon}")
        if not 0 <= index < len(self):
            raise IndexError(f"{self.name}: index {index} outside 0..{len(self) - 1}")
        poses, lift = self.poses(), self.lift()
        period_ns = 1e9 / self.frequency_hz
        return FramePair(
            pc0=lift_points(read_scan(self.scans[index], self.bin_columns), lift),
            pc1=lift_points(read_scan(self.scans[index + horizon], self.bin_columns), lift),
            ego1_from_ego0=None if poses is not None else self._drive_motion(index, horizon),
            pose0=None if poses is None else lift_pose(poses[index], lift),
            pose1=None if poses is None else lift_pose(poses[index + horizon], lift),
            dt=horizon / self.frequency_hz,
            log_id=self.root.name,
            sample_id=self.sample_id(index) + ("" if horizon == 1 else f"+{horizon}"),
            timestamp0_ns=int(round(index * period_ns)),
            timestamp1_ns=int(round((index + horizon) * period_ns)),
            source=str(self.scans[index]),
        )
