"""The refinement dial on real scans: whole-call time of a trained student alone, with the Predictor's ICP
refinement (``fastflow3d.inference.refine``) and of the teacher, on the shipped KITTI HDL-64 pair and the Argoverse 2
pair.

    .venv/bin/python benchmarks/bench_refine.py --model <export dir> [--runs 20] [--warmup 3] [--scans kitti,av2]

Ego motion and ground masks are given (computed once beforehand with the student's preprocessing: KISS-ICP and
Patchwork++), as in ``bench_latency.py``'s ``given`` regime; the teacher gets the same ego motion and masks. The
student runs as ``Predictor.load`` picks (ONNX Runtime, tuned, on the CPU); the three calls take turns within each
run. These scans have no ground-truth flow: the accuracy side of the dial is ``eval.py ... method=[ego,icpflow,
student,student+refine]`` on the synthetic test split (BENCHMARKS.md). Prints median and p90 ms, Hz, and for the
refinement the share of the network's points whose flow ICP replaced and their median change (m).
"""

from __future__ import annotations

import argparse
import os
import statistics

import numpy as np
from bench_latency import TEACHERS, read_scans, timed  # this folder is first on sys.path when run as a script

from fastflow3d.inference.predictor import Predictor
from icpflow.preprocess import lift_points, lift_transform
from icpflow.teacher import ICPFlow

#: metres of each scan's origin above the ground (KITTI's velodyne frame; the AV2 ego frame is the model's own)
SENSOR_HEIGHTS = {"kitti": 1.73, "av2": None}


def scan_calls(model: str, scan: str, pc0: np.ndarray, pc1: np.ndarray):
    """({method: call}, note on the refinement) for one scan pair; ego motion and ground masks computed once."""
    preprocessing = {"remove_ground": True, "teacher": TEACHERS[scan].to_dict()}
    options = {"preprocessing": preprocessing, "sensor_height": SENSOR_HEIGHTS[scan]}
    student = Predictor.load(model, **options)
    refined = Predictor.load(model, **options, refine=True)
    estimate = student.predict(pc0, pc1)  # the given regime's inputs, outside the timing
    ego, g0, lift = estimate.ego1_from_ego0, estimate.ground0, estimate.lift
    g1 = student.ground_mask("ground1", lift_points(pc1, lift), None)
    teacher = ICPFlow(TEACHERS[scan])
    frame0, frame1, frame_ego = lift_points(pc0, lift), lift_points(pc1, lift), lift_transform(ego, lift)
    calls = {
        "student": lambda: student.predict(pc0, pc1, ego, g0, g1),
        "student+refine": lambda: refined.predict(pc0, pc1, ego, g0, g1),
        "teacher": lambda: teacher(frame0, frame1, frame_ego, g0, g1),
    }
    plain, better = calls["student"](), calls["student+refine"]()
    change = np.linalg.norm(better.flow - plain.flow, axis=1)[better.refined]
    note = f"{better.refined.sum() / max(1, better.in_grid.sum()):.1%} of the network's points refined"
    return calls, note + (f", median change {np.median(change):.3f} m" if len(change) else "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="an export directory (or .ckpt)")
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--scans", default="kitti,av2")
    args = parser.parse_args()
    rows = []
    for scan in [s.strip() for s in args.scans.split(",") if s.strip()]:
        data = read_scans(scan, 0)
        if data is None:
            print(f"{scan}: no scans under ../shared/data; no rows")
            continue
        calls, note = scan_calls(args.model, scan, *data)
        for name, times in timed(calls, args.runs, args.warmup).items():
            rows.append((scan, len(data[0]), name, times, note if name == "student+refine" else ""))
    print("| scan | points pc0 | method | median ms | p90 ms | Hz | refinement |")
    print("|---|---|---|---|---|---|---|")
    for scan, points, name, times, note in rows:
        median, p90 = statistics.median(times), float(np.percentile(times, 90))
        print(f"| {scan} | {points} | {name} | {1000 * median:.1f} | {1000 * p90:.1f} | {1 / median:.1f} | {note} |")
    print(f"median and p90 of {args.runs} calls after {args.warmup}; load average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
