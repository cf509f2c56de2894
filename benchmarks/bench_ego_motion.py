"""What the ego-motion estimate (``icpflow.teacher.ego_motion``, the Predictor's and the teacher's step when no
poses are given) is made of, and how close each part gets to the true motion.

    .venv/bin/python benchmarks/bench_ego_motion.py [--repeats 5]

Per pair of real scans (median of ``repeats`` runs after one warm-up, seconds in ms):
* ``KISS-ICP pair``: ``kiss_icp_motion``, what every stateless call pays (pc0 then pc1 registered by a fresh KISS-ICP);
* ``KISS-ICP one frame``: pc1 alone registered onto a KISS-ICP that already holds pc0, what an estimator that keeps
  KISS-ICP between frames would pay per frame;
* ``refinement``: ``refine_motion`` (point-to-plane ICP of the down-sampled scans from the KISS-ICP estimate);
* errors against the true motion where it is known (translation cm / rotation degrees of ``inv(truth) @ estimate``):
  Argoverse 2's shipped pair (``ego_motion.npz``) and KITTI odometry sequence 01's frames 0 -> 1 and 1 -> 2 (ground-
  truth poses); the KITTI HDL-64E scans have none.
Preset ``av2``'s ego-motion settings (``ICPFlowConfig.preset("av2").ego_motion``, the Predictor's default).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from bench_teacher import DATA, read_av2, read_kitti

from icpflow.geometry import pose_error, relative_transform
from icpflow.teacher.config import ICPFlowConfig
from icpflow.teacher.ego_motion import kiss_icp_motion, kiss_odometry, refine_motion


def cases() -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]]:
    """(name, pc0, pc1, true ego1_from_ego0 or None) for each shipped pair that is present."""
    found = []
    kitti = read_kitti()
    if kitti is not None:
        found.append(("KITTI HDL-64E 000000 -> 000001", kitti[0], kitti[1], None))
    av2 = read_av2()
    if av2 is not None:
        found.append(("AV2 sweeps 0 -> 1", av2[0], av2[1], av2[2]))
    seq01 = DATA / "kitti_odometry_seq01" / "kitti_odom_seq01_frames000-002_with_gt_poses.npz"
    if seq01.is_file():
        frames = np.load(seq01)
        poses = frames["velo_poses_world"]
        for k in range(2):
            truth = relative_transform(poses[k], poses[k + 1])
            found.append((f"KITTI seq 01 {k} -> {k + 1}", frames[f"points{k}"], frames[f"points{k + 1}"], truth))
    return found


def errors(estimate: np.ndarray, truth: np.ndarray | None) -> str:
    if truth is None:
        return "-"
    translation, angle = pose_error(estimate, truth)
    return f"{100 * translation:.2f} / {angle:.3f}"


def median_ms(function, arguments: tuple, repeats: int) -> float:
    """Median ms of ``function(*arguments)`` over ``repeats`` calls after one warm-up call."""
    function(*arguments)
    walls = []
    for _ in range(repeats):
        tic = time.perf_counter()
        function(*arguments)
        walls.append(time.perf_counter() - tic)
    return 1e3 * statistics.median(walls)


def one_frame_ms(pc0, pc1, cfg, repeats: int) -> float:
    """Median ms of registering pc1 onto a KISS-ICP that holds pc0 (the odometry set up outside the timing)."""
    walls = []
    for _ in range(repeats + 1):
        odometry = kiss_odometry(cfg)
        odometry.register_frame(np.asarray(pc0, np.float64), np.zeros(0))
        tic = time.perf_counter()
        odometry.register_frame(np.asarray(pc1, np.float64), np.zeros(0))
        walls.append(time.perf_counter() - tic)
    return 1e3 * statistics.median(walls[1:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    cfg = ICPFlowConfig.preset("av2")
    found = cases()
    if not found:
        raise SystemExit(f"bench_ego_motion: no shipped scans under {DATA}")
    print(f"preset av2 ego motion, median of {args.repeats} after a warm-up; ms; errors cm / degrees against the truth")
    head = ["pair", "KISS-ICP pair", "KISS-ICP one frame", "refinement", "error, KISS-ICP", "error, + refinement"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for name, pc0, pc1, truth in found:
        kiss = kiss_icp_motion(pc0, pc1, cfg)
        refined = refine_motion(pc0, pc1, kiss, cfg)
        pair = median_ms(kiss_icp_motion, (pc0, pc1, cfg), args.repeats)
        frame = one_frame_ms(pc0, pc1, cfg, args.repeats)
        refine = median_ms(refine_motion, (pc0, pc1, kiss, cfg), args.repeats)
        cells = [name, f"{pair:.1f}", f"{frame:.1f}", f"{refine:.1f}", errors(kiss, truth), errors(refined, truth)]
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
