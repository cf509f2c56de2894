"""The teacher on real points: false motion of static structure, the moving/static split of labelled movers and the
ego error, on the real pairs beside the checkout, for whole scans and for scans whose ground is already removed:
the 30 KITTI sequence 00 pairs (``../shared/data/kitti_seq00_pairs``: exact poses, per-point moving labels; the
``kitti`` teacher), KITTI 01's two pairs (exact poses; cars left out of the score, parked and moving ones not told
apart; the ``kitti`` teacher) and the AV2 pair (flow labels; the ``av2`` teacher with its per-point times).

    python -m benchmarks.teacher_real_pairs [--pairs N] [--datasets kitti00,kitti01,av2]
        [--variants "given,own,given no ground,own no ground"] [--teacher FIELD=VALUE ...]

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

from benchmarks.common import DATA, SEQ01, cpu_name, literal_overrides
from benchmarks.eval_teacher import dataset_teacher
from icpflow.core.geometry import ego_flow, invert, pose_error, relative_transform, transform_points
from icpflow.scans.preprocess import lift_points, lift_transform
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
#: m: KITTI 01's HDL-64E above the road (``conf/dataset/kitti.yaml``'s sensor height): its scans are lifted by it
KITTI_SENSOR_HEIGHT = 1.73
#: KITTI 01's learning-map classes of the ground (road, terrain) and of cars (left out: parked or moving)
KITTI01_GROUND, KITTI01_CAR = (9, 17), 1


def read_pair(path: Path) -> dict:
    """One pair in the project's conventions: pc0, pc1 (N, 3) float32, ego1_from_ego0, the moving0 and
    ground0 / ground1 masks and pc0's instance ids ``instance0``."""
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
        "instance0": data["inst_label_s"].astype(np.int64),
        "ground0": np.isin(data["sem_label_s"] & 0xFFFF, GROUND_CLASSES),
        "ground1": np.isin(data["sem_label_t"] & 0xFFFF, GROUND_CLASSES),
    }


def read_kitti01() -> list[dict]:
    """KITTI 01's two pairs as :func:`read_pair` gives a pair, lifted into the height frame; its cars are neither
    static nor movers (``unscored0``), since the labels do not tell parked ones from moving ones."""
    data = np.load(SEQ01)
    pairs = []
    for i in range(2):
        labels0, labels1 = data[f"labels{i}"].reshape(-1), data[f"labels{i + 1}"].reshape(-1)
        ego = relative_transform(data["velo_poses_world"][i], data["velo_poses_world"][i + 1])
        pairs.append(
            {
                "name": f"kitti01_{i}_{i + 1}",
                "pc0": lift_points(data[f"points{i}"].astype(np.float32), KITTI_SENSOR_HEIGHT),
                "pc1": lift_points(data[f"points{i + 1}"].astype(np.float32), KITTI_SENSOR_HEIGHT),
                "ego1_from_ego0": lift_transform(ego, KITTI_SENSOR_HEIGHT),
                "moving0": np.zeros(len(labels0), bool),
                "unscored0": labels0 == KITTI01_CAR,
                "instance0": np.zeros(len(labels0), np.int64),
                "ground0": np.isin(labels0, KITTI01_GROUND),
                "ground1": np.isin(labels1, KITTI01_GROUND),
            }
        )
    return pairs


def read_av2() -> list[dict]:
    """The AV2 pair as :func:`read_pair` gives a pair: movers are its flow labels' dynamic points, the ground its
    labels' (pc0) and the map's (pc1); with its per-point times."""
    from icpflow.datasets.av2 import AV2Dataset

    pair = AV2Dataset(DATA / "av2", split="val", ground_threshold=0.4).pair(0)
    return [
        {
            "name": "av2",
            "pc0": pair.pc0,
            "pc1": pair.pc1,
            "ego1_from_ego0": pair.ego1_from_ego0,
            "moving0": pair.dynamic.astype(bool),
            "instance0": np.zeros(len(pair.pc0), np.int64),
            "ground0": pair.ground0,
            "ground1": pair.ground1,
            "times": {"time0": pair.time0, "time1": pair.time1, "dt": pair.dt},
        }
    ]


#: dataset -> (its pairs' reader, the ``label.py dataset=`` whose teacher runs on them)
DATASETS = {
    "kitti00": (lambda: [read_pair(path) for path in sorted(PAIRS.glob("*.npz"))], "kitti"),
    "kitti01": (read_kitti01, "kitti"),
    "av2": (read_av2, "av2"),
}


def plane_fit(pair: dict, ego: np.ndarray) -> float:
    """Median point-to-plane distance (m) of pc0's static points moved by ``ego`` onto pc1's local planes (points
    with no pc1 point within 0.5 m left out): how well an ego motion lays the static scene onto the next scan,
    whatever the dataset's poses say."""
    from scipy.spatial import cKDTree

    from icpflow.teacher.registration.icp import normals

    target = pair["pc1"].astype(np.float64)
    moved = transform_points(ego, pair["pc0"][~pair["moving0"]].astype(np.float64))
    distance, nearest = cKDTree(target).query(moved)
    residual = np.abs(np.einsum("ij,ij->i", moved - target[nearest], normals(target)[nearest]))
    return float(np.median(residual[distance < 0.5]))


def score(pair: dict, flow: np.ndarray, ego: np.ndarray) -> dict:
    """The pair's static residual (mean, p95), share of static points moved, movers found, the ego error and the
    static error of the ego motion used alone (0 where it was given)."""
    truth = ego_flow(pair["pc0"], pair["ego1_from_ego0"])
    residual = np.linalg.norm(flow - truth, axis=1)
    ego_only = np.linalg.norm(ego_flow(pair["pc0"], ego) - truth, axis=1)  # the flow of the ego motion used
    moving, ground = pair["moving0"], pair["ground0"] | pair.get("unscored0", False)
    scene = pair.get("whole", pair)  # the plane fit on the whole scans, ground included
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
        "fit_gain": plane_fit(scene, pair["ego1_from_ego0"]) - plane_fit(scene, ego),
    }


def variant_inputs(pair: dict, variant: str) -> tuple[dict, tuple]:
    """(the pair as ``variant`` gives it, ``ICPFlow``'s arguments for it): with ``no ground`` the labelled ground's
    points are dropped from both scans and no ground mask is passed; ``given`` passes the ego motion."""
    if variant not in VARIANTS:
        raise SystemExit(f"teacher_real_pairs: unknown variant {variant!r} (one of {', '.join(VARIANTS)})")
    grounds = (None, None)
    if "no ground" in variant:
        keep0, keep1 = ~pair["ground0"], ~pair["ground1"]
        per_point0 = ("pc0", "moving0", "instance0", "ground0", "unscored0")
        pair = {key: value[keep0] if key in per_point0 else value for key, value in pair.items()} | {"whole": pair}
        pair["pc1"], pair["ground1"] = pair["pc1"][keep1], pair["ground1"][keep1]
        if "times" in pair:
            times = pair["times"]
            pair["times"] = {"time0": times["time0"][keep0], "time1": times["time1"][keep1], "dt": times["dt"]}
        grounds = (np.zeros(len(pair["pc0"]), bool), np.zeros(len(pair["pc1"]), bool))
    given = pair["ego1_from_ego0"] if variant.startswith("given") else None
    times = pair.get("times", {})
    return pair, (pair["pc0"], pair["pc1"], given, *grounds, times.get("time0"), times.get("time1"))


def run(teacher: ICPFlow, pair: dict, variant: str) -> tuple[dict, float]:
    """The teacher on one pair as ``variant`` says; (its scores, seconds)."""
    pair, inputs = variant_inputs(pair, variant)
    start = time.perf_counter()
    result = teacher(*inputs, dt=pair.get("times", {}).get("dt"))
    seconds = time.perf_counter() - start
    return score(pair, result.flow, result.ego1_from_ego0), seconds


def _mean(values: list[float]) -> float:
    """The mean of the finite values (NaN where none is: a dataset without labelled movers)."""
    finite = [value for value in values if np.isfinite(value)]
    return float(np.mean(finite)) if finite else float("nan")


def summary(rows: list[dict]) -> str:
    """One table row over the pairs: static mean and p95 (means over pairs), pairs over 5 cm, the worst pair, movers
    found, static points moved, ego error p95."""
    mean = {key: _mean([row[key] for row in rows]) for key in rows[0] if key != "name"}
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
    parser.add_argument("--pairs", type=int, default=30, help="the first N pairs of each dataset")
    parser.add_argument("--datasets", default=",".join(DATASETS))
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument(
        "--teacher", action="append", default=[], metavar="FIELD=VALUE", help="an ICPFlowConfig override (repeatable)"
    )
    args = parser.parse_args(argv)
    fields = literal_overrides(args.teacher, parser, "--teacher")
    print(f"teacher overrides {fields or 'none'}; {cpu_name()}")
    print(
        "| dataset | variant | static residual mean (m) | static p95 | pairs over 5 cm | worst pair | movers found | "
        "static points moved | ego error p95 (m) | ego-only flow's static error | ego fits better than the poses | "
        "s/pair |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name in args.datasets.split(","):
        if name not in DATASETS:
            raise SystemExit(f"teacher_real_pairs: unknown dataset {name!r} (one of {', '.join(DATASETS)})")
        reader, teacher_name = DATASETS[name]
        try:
            pairs = reader()[: args.pairs]
        except (OSError, FileNotFoundError) as error:
            print(f"| {name} | absent: {error} |", flush=True)
            continue
        teacher = ICPFlow(dataset_teacher(teacher_name, fields))
        for variant in args.variants.split(","):
            results = [run(teacher, pair, variant.strip()) for pair in pairs]
            seconds = float(np.median([s for _, s in results]))
            print(f"| {name} | {variant} | {summary([r for r, _ in results])} | {seconds:.2f} |", flush=True)


if __name__ == "__main__":
    main()
