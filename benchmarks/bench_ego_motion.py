"""Ego motion from the scans alone (``icpflow.scans.odometry``): its error against true poses, pairwise and per drive.

    .venv/bin/python -m benchmarks.bench_ego_motion [--frames 100] [--seeds 0,1,2] [--beams 64,32]
        [--ground estimated|world] [--methods drive,pair]

Sequences: synthetic drives of ``--frames`` frames (the test split; each seed draws the ego's speed, 0-20 m/s, and
turns) at each beam count, KITTI odometry sequence 01 frames 0-2 (true poses; lifted 1.73 m into the height frame)
and Argoverse 2's shipped pair (``ego_motion.npz``). Each scan's ground comes from ``icpflow.scans.ground`` with the
dataset's settings (``--ground estimated``: its surface, ``GroundSegmenter.masks``, what a user gets) or from the
world's exact masks (``world``,
synthetic only). Methods: ``drive`` (one ``Odometry`` over the whole sequence, as ``label.py`` and a stream run it)
and ``pair`` (``estimate_ego_motion`` on each consecutive pair alone: no map, no motion model, as the teacher and
the Predictor run a lone pair). Prints, per sequence and over all synthetic pairs of each beam count, the
translation error (cm: median / p95 / max) and the rotation error (degrees: median / p95 / max) of
``inv(truth) @ estimate``, the steps with no estimate, and the median ms per step (the ground not included).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from benchmarks.common import DATA, SEQ01
from icpflow.core.geometry import invert, pose_error
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.scans.ground import GroundSegmenter
from icpflow.scans.odometry import Odometry, estimate_ego_motion
from icpflow.scans.preprocess import HeightFrame, Preprocessing
from icpflow.teacher.config import GroundConfig, ICPFlowConfig


def sequences(args):
    """(name, group, scans, ground masks, true ego1_from_ego0 per step)."""
    world = args.ground == "world"
    for beams in [int(b) for b in args.beams.split(",")]:
        for seed in [int(s) for s in args.seeds.split(",")]:
            data = SyntheticDataset(
                split="test", num_sequences=1, frames_per_sequence=args.frames, beams=beams, seed=seed
            )
            pairs = [data[i] for i in range(len(data))]
            scans = [pairs[0].pc0] + [pair.pc1 for pair in pairs]
            segmenter = GroundSegmenter(Preprocessing())
            grounds = (
                [pairs[0].ground0] + [p.ground1 for p in pairs] if world else [segmenter.masks(s)[1] for s in scans]
            )
            yield (
                f"synthetic {beams} beams, seed {seed}",
                f"synthetic {beams} beams",
                scans,
                grounds,
                [pair.ego1_from_ego0 for pair in pairs],
            )
    if SEQ01.is_file():
        with np.load(SEQ01) as data:
            scans = [data[f"points{i}"][:, :3].astype(np.float32) + np.float32([0, 0, 1.73]) for i in range(3)]
            poses = data["velo_poses_world"]
        segmenter = GroundSegmenter(Preprocessing(HeightFrame(0.0), GroundConfig(sensor_height=1.73)))
        truth = [invert(poses[i + 1]) @ poses[i] for i in range(2)]
        yield "KITTI seq 01 frames 0-2", "KITTI", scans, [segmenter.masks(s)[1] for s in scans], truth
    logs = sorted((DATA / "av2" / "sensor" / "val").glob("*/"))
    if logs:
        import pandas as pd

        sweeps = sorted((logs[0] / "sensors" / "lidar").glob("*.feather"))[:2]
        scans = [pd.read_feather(s, columns=["x", "y", "z"]).to_numpy().astype(np.float32) for s in sweeps]
        truth = [np.load(logs[0] / "ego_motion.npz")["ego_motion"][0].astype(np.float64)]
        segmenter = GroundSegmenter(ICPFlowConfig.preset("av2"))
        yield "AV2 sweeps 0-1", "AV2", scans, [segmenter.masks(s)[1] for s in scans], truth


def estimates(method: str, scans, grounds, cfg):
    """(estimates per step (None: none), seconds per step)."""
    found, seconds = [], []
    if method == "drive":
        odometry = Odometry(cfg)
        odometry.step(scans[0], grounds[0])
        for scan, ground in zip(scans[1:], grounds[1:]):
            tic = time.perf_counter()
            found.append(odometry.step(scan, ground).ego1_from_ego0)
            seconds.append(time.perf_counter() - tic)
        return found, seconds
    for k in range(len(scans) - 1):
        tic = time.perf_counter()
        found.append(estimate_ego_motion(scans[k], scans[k + 1], cfg, grounds[k], grounds[k + 1]))
        seconds.append(time.perf_counter() - tic)
    return found, seconds


def row(name: str, method: str, errors: list, missing: int, seconds: list) -> str:
    cm = 100 * np.array([e[0] for e in errors])
    deg = np.array([e[1] for e in errors])
    return (
        f"| {name} | {method} | {len(errors) + missing} | {np.median(cm):.2f} / {np.percentile(cm, 95):.2f} / "
        f"{cm.max():.2f} | {np.median(deg):.3f} / {np.percentile(deg, 95):.3f} / {deg.max():.3f} | {missing} | "
        f"{1000 * statistics.median(seconds):.0f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--beams", default="64,32")
    parser.add_argument("--ground", choices=("estimated", "world"), default="estimated")
    parser.add_argument("--methods", default="drive,pair")
    args = parser.parse_args()
    cfg = ICPFlowConfig.preset("waymo").ego_motion
    methods = args.methods.split(",")
    print(f"ground: {args.ground}; errors of inv(truth) @ estimate")
    print("| sequence | method | steps | translation cm: median / p95 / max | rotation deg: median / p95 / max | "
          "no estimate | ms per step |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    pooled: dict = {}
    for name, group, scans, grounds, truth in sequences(args):
        for method in methods:
            found, seconds = estimates(method, scans, grounds, cfg)
            errors = [pose_error(e, t) for e, t in zip(found, truth) if e is not None]
            missing = sum(e is None for e in found)
            print(row(name, method, errors, missing, seconds), flush=True)
            everything = pooled.setdefault((group, method), [[], 0, []])
            everything[0] += errors
            everything[1] += missing
            everything[2] += seconds
    for (group, method), (errors, missing, seconds) in pooled.items():
        if group.startswith("synthetic"):
            print(row(f"all {group}", method, errors, missing, seconds))


if __name__ == "__main__":
    main()
