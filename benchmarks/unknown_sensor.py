"""Raw scans of an unknown sensor (issue 21): ground and static flow on KITTI sequence 01, no poses, no masks.

    .venv/bin/python benchmarks/unknown_sensor.py [--export DIR] [--shards DIR]

On the three frames of ``../shared/data/kitti_odometry_seq01`` (exact poses; SemanticKITTI labels, every non-car
point static) it prints:

1. the ground fraction and its agreement with SemanticKITTI's ground (road, parking, sidewalk, other-ground,
   terrain) of each way of finding the ground: the synthetic world's settings on the raw velodyne frame (what a
   synthetic-trained model did before the height frame), the same settings after the Predictor's lift (``auto``,
   the ground estimated below the sensor), ``dataset=kitti`` (the reader's 1.73 m lift and its teacher) and
   ``dataset=sequence`` (the folder reader's estimated lift and its teacher, as ``label.py dataset=sequence``);
2. the static EPE (mean over the non-car, non-ground points within 32 m, against the exact poses) of the teacher
   with and without poses and, with ``--export``, of a student through the ``Predictor`` with the raw velodyne frame
   (``sensor_height=0``: the frame mismatch before) and with the default frame check, without poses, and told the
   height with the exact poses (what is left is the network's);
3. with ``--shards`` (a ``label.py dataset=sequence`` out_dir of these frames without poses), the same scores of
   the stored labels.
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np

from icpflow import options as icpflow_options
from icpflow.geometry import ego_flow, relative_transform
from icpflow.ground import GroundSegmenter
from icpflow.preprocess import Preprocessing, estimate_ground_height, lift_points, lift_transform
from icpflow.teacher import ICPFlow
from icpflow.teacher.config import teacher_config

ROOT = Path(__file__).resolve().parents[1]
SEQ01 = ROOT.parent / "shared" / "data" / "kitti_odometry_seq01" / "kitti_odom_seq01_frames000-002_with_gt_poses.npz"
GROUND_CLASSES = (9, 10, 11, 12, 17)  # SemanticKITTI learning map: road, parking, sidewalk, other-ground, terrain
CAR = 1
CROP = 32.0


def dataset_teacher(name: str):
    """The teacher that ``label.py dataset=<name>`` runs."""
    from hydra import compose, initialize_config_dir

    icpflow_options.register()  # the schemas the configs extend, as the entry script stores them
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return teacher_config(compose("label", [f"dataset={name}", "dataset.root=unused"]))


def ground_table(data) -> None:
    synthetic = Preprocessing.from_teacher(dataset_teacher("synthetic"))
    ways = {
        "synthetic settings, raw velodyne frame (before)": lambda p: GroundSegmenter(synthetic)(p),
        "synthetic settings, lifted by the estimated ground (Predictor auto)": lambda p: GroundSegmenter(synthetic)(
            lift_points(p, -estimate_ground_height(p))
        ),
        "dataset=kitti (reader lift 1.73 m, its teacher)": lambda p: GroundSegmenter(dataset_teacher("kitti"))(
            lift_points(p, 1.73)
        ),
        "dataset=sequence (lift estimated from the first scan, its teacher)": lambda p: GroundSegmenter(
            dataset_teacher("sequence")
        )(lift_points(p, -estimate_ground_height(data["points0"]))),
    }
    print("\nGround on KITTI seq 01 frames 0-2 against SemanticKITTI (road, parking, sidewalk, other-ground, terrain)")
    print("| ground from | ground fraction | labelled ground | agreement |")
    print("|---|---|---|---|")
    for name, find in ways.items():
        fractions, truths, agreements = [], [], []
        for frame in range(3):
            points = data[f"points{frame}"].astype(np.float32)
            truth = np.isin(data[f"labels{frame}"].reshape(-1), GROUND_CLASSES)
            mask = find(points)
            fractions.append(mask.mean())
            truths.append(truth.mean())
            agreements.append((mask == truth).mean())
        print(f"| {name} | {np.mean(fractions):.1%} | {np.mean(truths):.1%} | {np.mean(agreements):.1%} |")


def static_points(data, frame: int) -> np.ndarray:
    labels = data[f"labels{frame}"].reshape(-1)
    points = data[f"points{frame}"]
    inside = np.abs(points[:, :2]).max(axis=1) < CROP
    return inside & (labels != CAR) & ~np.isin(labels, GROUND_CLASSES)


def static_epe(flow: np.ndarray, data, frame: int, among: np.ndarray | None = None) -> float:
    """Mean EPE (m) over the static non-ground points within the crop (and ``among``, e.g. the student's in-grid
    points: those the network predicted)."""
    pc0 = data[f"points{frame}"].astype(np.float32)
    truth = ego_flow(pc0, relative_transform(data["velo_poses_world"][frame], data["velo_poses_world"][frame + 1]))
    keep = static_points(data, frame) & (True if among is None else among)
    return float(np.linalg.norm(flow[keep] - truth[keep], axis=1).mean()) if keep.any() else float("nan")


def flow_table(data, export: Path | None, shards: Path | None) -> None:
    rows: dict[str, list] = {}
    kitti, sequence = ICPFlow(dataset_teacher("kitti")), ICPFlow(dataset_teacher("sequence"))
    lift = -estimate_ground_height(data["points0"])
    for frame in range(2):
        pc0, pc1 = (lift_points(data[f"points{k}"].astype(np.float32), 1.73) for k in (frame, frame + 1))
        truth = relative_transform(data["velo_poses_world"][frame], data["velo_poses_world"][frame + 1])
        tic = time.perf_counter()
        result = kitti(pc0, pc1, lift_transform(truth, 1.73))
        rows.setdefault("teacher, dataset=kitti, exact poses", []).append(
            (static_epe(result.flow, data, frame), float("nan"), 0, result.ground0.mean(), time.perf_counter() - tic)
        )
        tic = time.perf_counter()
        raw0, raw1 = (lift_points(data[f"points{k}"].astype(np.float32), lift) for k in (frame, frame + 1))
        result = sequence(raw0, raw1)
        rows.setdefault("teacher, dataset=sequence, no poses (KISS-ICP)", []).append(
            (static_epe(result.flow, data, frame), float("nan"), 0, result.ground0.mean(), time.perf_counter() - tic)
        )
    if export is not None:
        from fastflow3d.inference.predictor import Predictor

        variants = (
            ("raw velodyne frame, sensor_height=0 (before), no poses", 0.0, False),
            ("default frame check, no poses", None, False),
            ("sensor_height=1.73, exact poses", 1.73, True),
        )
        for name, height, given in variants:
            predictor = Predictor.load(export, sensor_height=height)
            for frame in range(2):
                pc0, pc1 = (data[f"points{k}"].astype(np.float32) for k in (frame, frame + 1))
                poses = data["velo_poses_world"]
                ego = relative_transform(poses[frame], poses[frame + 1]) if given else None
                tic = time.perf_counter()
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    prediction = predictor.predict(pc0, pc1, ego)
                for warning in caught:
                    print(f"  ({name}, frame {frame}) warning: {warning.message}")
                rows.setdefault(f"student, {name}", []).append(
                    (
                        static_epe(prediction.flow, data, frame),
                        static_epe(prediction.flow, data, frame, prediction.in_grid),
                        int((static_points(data, frame) & prediction.in_grid).sum()),
                        prediction.ground0.mean(),
                        time.perf_counter() - tic,
                    )
                )
    if shards is not None:
        from icpflow.shards.reader import ShardDataset

        stored = ShardDataset(shards)
        for frame in range(min(2, len(stored))):
            sample = stored[frame]
            rows.setdefault(f"label.py dataset=sequence shards ({shards.name}), no poses", []).append(
                (static_epe(sample["flow"], data, frame), float("nan"), 0, sample["ground0"].mean(), float("nan"))
            )
    print(f"\nStatic EPE on KITTI seq 01 pairs 0->1, 1->2 (non-car, non-ground points within {CROP:g} m, exact poses)")
    print("| method | static EPE (m) | static EPE of the points the network predicted (m, count) | ground | s/pair |")
    print("|---|---|---|---|---|")
    for name, values in rows.items():
        epe, in_grid, count, ground, seconds = np.mean(values, axis=0)
        print(f"| {name} | {epe:.3f} | {in_grid:.3f} ({count:.0f}) | {ground:.1%} | {seconds:.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--export", type=Path, help="a student export directory (or .ckpt)")
    parser.add_argument("--shards", type=Path, help="label.py dataset=sequence out_dir of the seq 01 frames")
    args = parser.parse_args()
    if not SEQ01.is_file():
        raise SystemExit(f"unknown_sensor: {SEQ01} is absent (../shared/data)")
    data = np.load(SEQ01)
    ground_table(data)
    flow_table(data, args.export, args.shards)


if __name__ == "__main__":
    main()
