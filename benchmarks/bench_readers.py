"""Pairs per second of every dataset reader, on real samples where ../shared/data has them, else on files of
realistic size written in the real layout to a temporary folder.

    .venv/bin/python -m benchmarks.bench_readers [--repeats 5]

Each row: median over ``repeats`` runs of reading every pair of the dataset once (AV2: pair read + map ground +
annotation flow; "cold" builds a new reader per run, so it includes loading the log's tables and ground raster).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import DATA
from icpflow.core.open3d_loader import load_open3d
from icpflow.datasets.kitti import KittiOdometryDataset
from icpflow.datasets.pairs import NpzPairsDataset
from icpflow.datasets.pcaccumulation import PCAccumulationDataset
from icpflow.datasets.scan_folder import ScanSequenceDataset
from icpflow.datasets.zeroflow import ZeroFlowAV2Dataset

RNG = np.random.default_rng(0)


def cloud(count: int) -> np.ndarray:
    return RNG.uniform((-80, -80, -2), (80, 80, 4), (count, 3)).astype(np.float32)


def write_pcaccumulation(root: Path, frames: int, per_frame: int, samples: int = 3, waymo: bool = True) -> None:
    """Files in PCAccumulation's encoding: Waymo ``sem_labels`` (m,) = box type - 1 (0 vehicle, 1 pedestrian,
    2 background, 3 cyclist); nuScenes ``sem_labels`` for the anchor frame's points only."""
    (root / "val").mkdir(parents=True)
    for index in range(samples):
        count = frames * per_frame
        inst = RNG.integers(0, 20, count)
        sem = np.where(inst > 0, np.array([0, 1, 3])[inst % 3], 2)
        np.savez(
            root / "val" / f"{index:03d}.npz",
            raw_points=cloud(count),
            time_indice=np.repeat(np.arange(frames), per_frame).astype(np.int64),
            sd_labels=(inst > 15).astype(np.int64),
            fb_labels=(inst > 0).astype(np.int64),
            inst_labels=inst,
            sem_labels=sem if waymo else RNG.integers(0, 16, per_frame),
            ego_motion_gt=np.tile(np.eye(4, dtype=np.float32), (frames, 1, 1)),
            bbox_tsfm=np.tile(np.eye(4, dtype=np.float32), (20, frames, 1, 1)),
        )


def write_zeroflow(root: Path, count: int = 60_000, padded: int = 90_000, samples: int = 3) -> None:
    folder = root / "val_zero_flow" / "log"
    folder.mkdir(parents=True)
    for index in range(samples):
        pad = np.full((padded - count, 3), np.nan, np.float32)
        np.savez(
            folder / f"{index:06d}.npz",
            pc1=np.concatenate([cloud(count), pad]),
            pc2=np.concatenate([cloud(count), pad]),
            gt_flow_0_1=np.concatenate([np.zeros((count, 3), np.float32), pad]),
            pc1_flows_valid_idx=np.arange(count),
            pc2_flows_valid_idx=np.arange(count),
            pc1_classes=np.full(padded, -1),
            pc2_classes=np.full(padded, -1),
        )


def write_pairs(root: Path, count: int = 100_000, samples: int = 3) -> None:
    root.mkdir(parents=True)
    for index in range(samples):
        np.savez(root / f"{index:03d}.npz", pc0=cloud(count), pc1=cloud(count), ego1_from_ego0=np.eye(4),
                 flow=np.zeros((count, 3), np.float32), ground0=np.zeros(count, bool))  # fmt: skip


def write_scans(root: Path, suffix: str) -> None:
    """The six real HDL-64 scans (about 124k points each) rewritten in another format."""
    root.mkdir(parents=True)
    for path in sorted((DATA / "kitti_hdl64_scans").glob("*.bin")):
        points = np.fromfile(path, np.float32).reshape(-1, 4)[:, :3]
        if suffix == ".npy":
            np.save(root / f"{path.stem}.npy", points)
        else:
            o3d = load_open3d()
            cloud3d = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
            o3d.io.write_point_cloud(str(root / f"{path.stem}{suffix}"), cloud3d)


def measure(make, repeats: int) -> tuple[int, int, float]:
    """(pairs per run, points in pc0 of the first pair, median seconds per pair)."""
    dataset = make()
    points = len(dataset.pair(0).pc0)  # also warms imports and per-log caches
    per_pair = []
    for _ in range(repeats):
        start = time.perf_counter()
        for index in range(len(dataset)):
            dataset.pair(index)
        per_pair.append((time.perf_counter() - start) / len(dataset))
    return len(dataset), points, statistics.median(per_pair)


def measure_cold(make, repeats: int) -> tuple[int, int, float]:
    """Like :func:`measure` for the first pair of a newly built reader each run (no caches)."""
    times, points = [], 0
    for _ in range(repeats):
        start = time.perf_counter()
        points = len(make().pair(0).pc0)
        times.append(time.perf_counter() - start)
    return 1, points, statistics.median(times)


def readers(tmp: Path) -> list[tuple[str, object, object]]:
    """(row name, measuring function, reader factory), writing the temporary datasets they need."""
    rows = []
    if (DATA / "av2").is_dir():
        from icpflow.datasets.av2 import AV2Dataset

        def make_av2():
            return AV2Dataset(DATA / "av2", "val")

        rows += [
            ("av2 (real log, warm)", measure, make_av2),
            ("av2 (real log, cold: + raster)", measure_cold, make_av2),
        ]
    write_pcaccumulation(tmp / "waymo", 5, 60_000)
    write_pcaccumulation(tmp / "nuscenes", 11, 30_000, waymo=False)
    write_zeroflow(tmp / "zeroflow")
    write_pairs(tmp / "pairs")
    rows += [
        ("waymo (PCAccumulation 5 x 60k, k=1)", measure, lambda: PCAccumulationDataset(tmp / "waymo", "val", 5, 10.0)),
        ("nuscenes (PCAccumulation 11 x 30k, k=1)", measure,
         lambda: PCAccumulationDataset(tmp / "nuscenes", "val", 11, 20.0, "nuscenes", sem_labels="nuscenes")),
        ("zeroflow_av2 (60k of 90k padded)", measure, lambda: ZeroFlowAV2Dataset(tmp / "zeroflow", "val")),
        ("pairs (.npz, 100k + flow)", measure, lambda: NpzPairsDataset(tmp / "pairs")),
    ]  # fmt: skip
    scans = DATA / "kitti_hdl64_scans"
    if scans.is_dir():
        rows += [
            ("kitti (real .bin scans)", measure, lambda: KittiOdometryDataset(scans)),
            ("sequence .bin (real scans)", measure, lambda: ScanSequenceDataset(scans)),
        ]
        for suffix in (".npy", ".ply", ".pcd"):
            write_scans(tmp / suffix[1:], suffix)
            rows.append((f"sequence {suffix} (real scans)", measure,
                         lambda folder=tmp / suffix[1:]: ScanSequenceDataset(folder)))  # fmt: skip
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    print(f"{'reader':<42} {'pairs':>5} {'pc0 points':>10} {'ms/pair':>8} {'pairs/s':>8}")
    with tempfile.TemporaryDirectory() as tmp:
        for name, how, make in readers(Path(tmp)):
            pairs, points, seconds = how(make, args.repeats)
            print(f"{name:<42} {pairs:>5} {points:>10} {seconds * 1e3:>8.1f} {1 / seconds:>8.1f}", flush=True)


if __name__ == "__main__":
    main()
