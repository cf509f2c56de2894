"""KITTI odometry: velodyne scans with the benchmark's ground-truth poses where they exist.

Layout (the official download): ``<root>/sequences/<seq>/velodyne/<frame>.bin`` (float32 rows x, y, z,
reflectance), ``<root>/sequences/<seq>/calib.txt`` (its ``Tr:`` line: velodyne -> left camera, 3 x 4),
``<root>/sequences/<seq>/times.txt`` (seconds, optional) and ``<root>/poses/<seq>.txt`` (12 values a line: the
left camera's pose in the first camera frame; sequences 00-10 only). ``root`` may also be a bare folder of
``.bin`` scans: one sequence named after the folder, without poses.

What a pair holds: ``pc0``/``pc1`` (N, 3) float32 in the project's height frame (``icpflow.scans.preprocess``): each
velodyne frame lifted by ``sensor_height`` (1.73 m, the HDL-64E above the road; 0 keeps the raw velodyne frame), so
the origin is on the ground below the sensor and the ground lies near z = 0, as in the synthetic world; where poses
exist, ``pose0``/``pose1`` = ``inv(Tr) @ T_cam @ Tr`` (world_from_velodyne, world = the first camera frame) lowered
onto that origin, and hence ``ego1_from_ego0``; without poses those are None (the teacher estimates ego motion).
KITTI odometry has no object flow: no ``flow``, ``classes``, ``dynamic`` or ground. ``dt`` from ``times.txt``,
else 0.1 s per frame.

Splits (SemanticKITTI's): train 00-07, 09, 10; val 08; test 11-21; ``sequences`` overrides. Only sequences
present under ``root`` are used. Samples are the scans t of each sequence for which t + ``max_horizon`` exists.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from icpflow.core.files import read_text
from icpflow.core.frame_pair import FramePair
from icpflow.core.geometry import invert
from icpflow.datasets.base import IndexedDataset, too_short
from icpflow.datasets.file_formats import BIN_COLUMNS, fail, natural_key, read_bin, read_pose_lines
from icpflow.scans.preprocess import lift_points, lift_pose

SPLITS = {
    "train": ["00", "01", "02", "03", "04", "05", "06", "07", "09", "10"],
    "val": ["08"],
    "test": [f"{n:02d}" for n in range(11, 22)],
}
SCAN_PERIOD_S = 0.1
SENSOR_HEIGHT = 1.73  # m: the HDL-64E above the road (KITTI's setup)


def read_calib_tr(path: Path) -> np.ndarray:
    """The (4, 4) float64 velodyne -> camera transform from the ``Tr:`` line of a KITTI ``calib.txt``."""
    try:
        lines = read_text(path).splitlines()
    except FileNotFoundError:
        raise fail(path, "file not found (needed to turn camera poses into velodyne poses)") from None
    for line in lines:
        if line.startswith("Tr:"):
            values = line.split()[1:]
            if len(values) != 12:
                raise fail(path, f"Tr has {len(values)} values, expected 12")
            transform = np.eye(4)
            transform[:3] = np.array(values, dtype=np.float64).reshape(3, 4)
            return transform
    raise fail(path, "no 'Tr:' line")


class KittiOdometryDataset(IndexedDataset):
    """KITTI odometry scan pairs with velodyne poses (see the module docstring)."""

    name = "kitti"

    def __init__(
        self,
        root: str | Path,
        split: str = "train",
        sequences: list[str] | None = None,
        max_horizon: int = 1,
        sensor_height: float = SENSOR_HEIGHT,
    ) -> None:
        self.root = Path(root)
        self.sensor_height = float(sensor_height)
        self.split = split
        self.max_horizon = int(max_horizon)
        if any(self.root.glob("*.bin")):
            found = {self.root.name: self.root}
            wanted = [self.root.name]
        else:
            found = {p.parent.name: p for p in sorted(self.root.glob("sequences/*/velodyne"))}
            if sequences is None and split not in SPLITS:
                raise ValueError(f"kitti: unknown split {split!r}; use one of {', '.join(SPLITS)} or give sequences")
            wanted = [f"{int(s):02d}" if str(s).isdigit() else str(s) for s in (sequences or SPLITS[split])]
        self._index_sequences(
            [(name, sorted(found[name].glob("*.bin"), key=natural_key)) for name in wanted if name in found]
        )
        if not self._sequences:
            have = ", ".join(found) or "none"
            raise fail(self.root, f"no velodyne scans for sequences {', '.join(wanted)}; found {have}")

    def why_empty(self) -> str:
        if self._index:
            return ""
        return too_short([(f"sequence {name}", len(scans)) for name, scans in self._sequences], self.max_horizon)

    def metadata(self) -> dict:
        return {**super().metadata(), "root": str(self.root), "split": self.split, "sensor_height": self.sensor_height,
                "sequences": [name for name, _ in self._sequences]}  # fmt: skip

    def _bare(self) -> bool:
        return not (self.root / "sequences").is_dir()

    def _poses(self, name: str, count: int) -> np.ndarray | None:
        """(count, 4, 4) world_from_velodyne poses of a sequence, or None where it has no pose file."""
        pose_path = self.root / "poses" / f"{name}.txt"
        if self._bare() or not pose_path.is_file():
            return None
        if ("poses", name) not in self._cache:
            camera = read_pose_lines(pose_path)
            if len(camera) < count:
                raise fail(pose_path, f"{len(camera)} poses for {count} scans")
            tr = read_calib_tr(self.root / "sequences" / name / "calib.txt")
            self._cache["poses", name] = lift_pose(invert(tr) @ camera @ tr, self.sensor_height)
        return self._cache["poses", name]

    def _times(self, name: str, count: int) -> np.ndarray:
        """(count,) float64 seconds of each scan: ``times.txt`` if present, else 0.1 s apart."""
        path = self.root / "sequences" / name / "times.txt"
        if self._bare() or not path.is_file():
            return np.arange(count) * SCAN_PERIOD_S
        if ("times", name) not in self._cache:
            try:
                times = np.loadtxt(path, dtype=np.float64, ndmin=1)
            except ValueError as error:
                raise fail(path, f"not a column of seconds: {error}") from None
            if len(times) < count:
                raise fail(path, f"{len(times)} times for {count} scans")
            self._cache["times", name] = times
        return self._cache["times", name]

    def pair(self, index: int, horizon: int = 1) -> FramePair:
        if not 1 <= horizon <= self.max_horizon:
            raise IndexError(f"{self.name}: horizon {horizon} outside 1..{self.max_horizon}")
        name, scans, t = self._frames(index)
        poses = self._poses(name, len(scans))
        times = self._times(name, len(scans))
        dt = float(times[t + horizon] - times[t])
        if not dt > 0:
            times_path = self.root / "sequences" / name / "times.txt"
            raise fail(times_path, f"times of scans {t} and {t + horizon} not increasing")
        return FramePair(
            pc0=lift_points(read_bin(scans[t], BIN_COLUMNS), self.sensor_height),
            pc1=lift_points(read_bin(scans[t + horizon], BIN_COLUMNS), self.sensor_height),
            pose0=None if poses is None else poses[t],
            pose1=None if poses is None else poses[t + horizon],
            dt=dt,
            log_id=name,
            sample_id=self.sample_id(index) + ("" if horizon == 1 else f"+{horizon}"),
            timestamp0_ns=int(round(times[t] * 1e9)),
            timestamp1_ns=int(round(times[t + horizon] * 1e9)),
            source=str(scans[t]),
        )
