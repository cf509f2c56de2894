"""The teacher on real points: false motion of static structure, the moving/static split of labelled movers and the
ego error, on the 30 real KITTI sequence 00 pairs beside the checkout (``../shared/data/kitti_seq00_pairs``: exact
poses, per-point moving labels), for whole scans and for scans whose ground is already removed.

    python -m benchmarks.teacher_real_pairs [--pairs N] [--variants "given,own,given no ground,own no ground"]
        [--teacher FIELD=VALUE ...]

Per pair, static points (``mot_label == 0``, ground classes left out of the score) have an exact FULL flow, the ego
motion's; their residual ``|flow - ego flow|`` is the teacher's false motion. A labelled mover counts as found where
its residual is over :data:`MOVING_M` (cars there move 0.5-1.5 m a frame); a static point over it is false motion.
Variants: the ego motion given (``given``) or the teacher's own (``own``, KISS-ICP), on the whole scans (the teacher's
own ground) or on the points off the labelled ground (``no ground``: what published methods are given; no ground
mask is passed, none is left). The dataset's poses are not exact to the centimetre: "ego fits better than the poses"
is the share of pairs where the ego motion used lays pc0's static points (ground included) closer to pc1's local
planes (median point-to-plane distance, :func:`plane_fit`) than the poses do, so an ego error of 1-2 cm there is
within the reference's own error.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks.common import DATA, cpu_name, literal_overrides
from benchmarks.eval_teacher import dataset_teacher
from icpflow.geometry import ego_flow, invert, pose_error, relative_transform, transform_points
from icpflow.preprocess import lift_points, lift_transform
from icpflow.teacher import ICPFlow

PAIRS = DATA / "kitti_seq00_pairs"
#: the folder's frame (x left, y up, z forward, camera origin) into the project's (x forward, y left, z up)
AXES = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
#: metres the road lies below the camera origin there: the scans are lifted by it into the height frame
LIFT = 1.8
#: raw SemanticKITTI classes of the ground: road, parking, sidewalk, other-ground, lane marking, terrain
GROUND_CLASSES = (40, 44, 48, 49, 60, 72)
#: residual (m) above which a point counts as moving
MOVING_M = 0.1
VARIANTS = ("given", "own", "given no ground", "own no ground")


def read_pair(path: Path) -> dict:
    """One pair in the project's conventions: pc0, pc1 (N, 3) float32, ego1_from_ego0, moving0 and ground0 masks."""
    data = np.load(path)
    turn = np.eye(4)
    turn[:3, :3] = AXES
    ego = turn @ relative_transform(data["pose_s"], data["pose_t"]) @ invert(turn)
    return {
        "name": path.stem,
        "pc0": lift_points(transform_points(turn, data["pc1"]).astype(np.float32), LIFT),
        "pc1": lift_points(transform_points(turn, data["pc2"]).astype(np.float32), LIFT),
        "ego1_from_ego0": lift_transform(ego, LIFT),
        "moving0": data["mot_label_s"] > 0,
        "ground0": np.isin(data["sem_label_s"] & 0xFFFF, GROUND_CLASSES),
        "ground1": np.isin(data["sem_label_t"] & 0xFFFF, GROUND_CLASSES),
    }


def plane_fit(pair: dict, ego: np.ndarray) -> float:
    """Median point-to-plane distance (m) of pc0's static points moved by ``ego`` onto pc1's local planes (points
    with no pc1 point within 0.5 m left out): how well an ego motion lays the static scene onto the next scan,
    whatever the dataset's poses say."""
    from scipy.spatial import cKDTree

    from icpflow.teacher.icp import normals

    target = pair["pc1"].astype(np.float64)
    moved = transform_points(ego, pair["pc0"][~pair["moving0"]].astype(np.float64))
    distance, nearest = cKDTree(target).query(moved)
    residual = np.abs(np.einsum("ij,ij->i", moved - target[nearest], normals(target)[nearest]))
    return float(np.median(residual[distance < 0.5]))


def score(pair: dict, flow: np.ndarray, ego: np.ndarray, keep: np.ndarray) -> dict:
    """The pair's static residual (mean, p95), share of static points moved, movers found, the ego error and the
    static error of the ego motion used alone (0 where it was given)."""
    truth = ego_flow(pair["pc0"][keep], pair["ego1_from_ego0"])
    residual = np.linalg.norm(flow - truth, axis=1)
    ego_only = np.linalg.norm(ego_flow(pair["pc0"][keep], ego) - truth, axis=1)  # the flow of the ego motion used
    moving, ground = pair["moving0"][keep], pair["ground0"][keep]
    static = residual[~moving & ~ground]
    translation, angle = pose_error(ego, pair["ego1_from_ego0"])
    return {
        "name": pair["name"],
        "static_mean": float(static.mean()),
        "static_p95": float(np.quantile(static, 0.95)),
        "static_moved": float((static > MOVING_M).mean()),
        "movers_found": float((residual[moving] > MOVING_M).mean()) if moving.any() else float("nan"),
        "ego_m": translation,
        "ego_deg": angle,
        "ego_only": float(ego_only[~moving & ~ground].mean()),
        "fit_gain": plane_fit(pair, pair["ego1_from_ego0"]) - plane_fit(pair, ego),
    }


def run(teacher: ICPFlow, pair: dict, variant: str) -> tuple[dict, float]:
    """The teacher on one pair as ``variant`` says; (its scores, seconds)."""
    keep0 = ~pair["ground0"] if "no ground" in variant else np.ones(len(pair["pc0"]), bool)
    keep1 = ~pair["ground1"] if "no ground" in variant else np.ones(len(pair["pc1"]), bool)
    pc0, pc1 = pair["pc0"][keep0], pair["pc1"][keep1]
    given = pair["ego1_from_ego0"] if variant.startswith("given") else None
    grounds = (np.zeros(len(pc0), bool), np.zeros(len(pc1), bool)) if "no ground" in variant else (None, None)
    start = time.perf_counter()
    result = teacher(pc0, pc1, given, *grounds)
    seconds = time.perf_counter() - start
    return score(pair, result.flow, result.ego1_from_ego0, keep0), seconds


def summary(rows: list[dict]) -> str:
    """One table row over the pairs: static mean and p95 (means over pairs), pairs over 5 cm, the worst pair, movers
    found, static points moved, ego error p95."""
    mean = {key: float(np.nanmean([row[key] for row in rows])) for key in rows[0] if key != "name"}
    worst = max(rows, key=lambda row: row["static_mean"])
    over = sum(row["static_mean"] > 0.05 for row in rows)
    ego_p95 = np.quantile([row["ego_m"] for row in rows], 0.95)
    return (
        f"{mean['static_mean']:.4f} | {mean['static_p95']:.4f} | {over} of {len(rows)} | {worst['static_mean']:.3f} "
        f"({worst['name']}) | {mean['movers_found']:.3f} | {mean['static_moved']:.4f} | {ego_p95:.4f} | "
        f"{mean['ego_only']:.4f} | {np.mean([row['fit_gain'] > 0 for row in rows]):.2f}"
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=30)
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument(
        "--teacher", action="append", default=[], metavar="FIELD=VALUE", help="an ICPFlowConfig override (repeatable)"
    )
    args = parser.parse_args(argv)
    fields = literal_overrides(args.teacher, parser, "--teacher")
    files = sorted(PAIRS.glob("*.npz"))[: args.pairs]
    if not files:
        raise SystemExit(f"teacher_real_pairs: no pairs in {PAIRS}")
    pairs = [read_pair(path) for path in files]
    teacher = ICPFlow(dataset_teacher("kitti", fields))
    print(f"KITTI 00 pairs: {len(pairs)}; teacher overrides {fields or 'none'}; {cpu_name()}")
    print(
        "| variant | static residual mean (m) | static p95 | pairs over 5 cm | worst pair | movers found | "
        "static points moved | ego error p95 (m) | ego-only flow's static error | ego fits better than the poses | "
        "s/pair |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for variant in args.variants.split(","):
        results = [run(teacher, pair, variant.strip()) for pair in pairs]
        seconds = float(np.median([s for _, s in results]))
        print(f"| {variant} | {summary([r for r, _ in results])} | {seconds:.2f} |", flush=True)


if __name__ == "__main__":
    main()
