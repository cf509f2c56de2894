"""Quality tables of the ICP-Flow teacher and its ablations: Argoverse 2 pair, KITTI sequence 01, synthetic val split.

    .venv/bin/python -m benchmarks.eval_teacher [--av2 [--av2-ground map|patchwork] [--no-times]] [--kitti]
        [--synthetic N [--split val|test]] [--variants "teacher,own ground,nothing given,kiss-icp ego,zero flow"]
        [--set FIELD=VALUE ...]

Scores come from ``icpflow.evaluation.metrics`` (the same code as eval.py): the paper's split into dynamic foreground,
static foreground and static background, point-weighted, ground excluded, in the dataset's crop (AV2 51.2 m, synthetic
32 m). Variants: the teacher (the dataset's preset), centroid initialisation, Hungarian association, KISS-ICP ego
motion (the given poses ignored: the pair's own odometry), the teacher's own ground (the dataset's masks withheld;
also with the ground method of older releases), nothing given (own ground and ego motion, pairwise; ``eval.py
method=icpflow-raw`` carries the odometry along a drive), and the zero (ego-compensated) flow. For AV2 it also
prints the protocol of ``tests/icpflow/teacher/test_teacher_real.py``: mean EPE over every point the official labels
call dynamic (ground included, no crop). ``--no-times`` withholds the sweeps' per-point capture times, so the de-skew
step does not run.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchmarks.common import DATA, SEQ01, compose, literal_overrides
from icpflow.core.geometry import ego_flow, pose_error, relative_transform
from icpflow.evaluation import metrics
from icpflow.teacher import ICPFlow, ICPFlowConfig
from icpflow.teacher.config import teacher_config

#: a variant key: the dataset's ground masks are not passed to the teacher
OWN_GROUND = "own ground"
VARIANTS = {
    "teacher": {},
    "centroid init": {"histogram.init": "centroid"},
    "hungarian": {"association.method": "hungarian"},
    "kiss-icp ego": {"ego_motion": {"method": "kiss_icp"}},
    # the dataset's ground masks withheld: the teacher's own ground (icpflow.scans.ground), with the given ego motion or
    # with its own (the pair's odometry) too; "older ground": the same with the ground of every release before
    "own ground": {OWN_GROUND: True},
    "own ground (older method)": {OWN_GROUND: True, "ground.method": "both"},
    "nothing given": {OWN_GROUND: True, "ego_motion": {"method": "kiss_icp"}},
    "zero flow": None,
}


def dataset_teacher(name: str, fields: dict) -> ICPFlowConfig:
    """The teacher that ``label.py dataset=<name>`` runs (its preset and ``dataset.teacher``), with ``fields``."""
    return teacher_config(compose("label", [f"dataset={name}"])).replace(**fields)


def run_variant(overrides, pairs, dataset: str, crop: float, use_ground: bool, use_times: bool, base: dict):
    """(point-weighted table of ``icpflow.evaluation.metrics``, median s/pair, mean EPE over each pair's ``dynamic``
    points)."""
    overrides = None if overrides is None else dict(overrides)
    withheld = (overrides or {}).pop(OWN_GROUND, False)  # popped whatever use_ground says: not a teacher field
    use_ground = use_ground and not withheld
    teacher = None if overrides is None else ICPFlow(dataset_teacher(dataset, {**base, **overrides}))
    scores, seconds, dynamic_errors = metrics.MetricAccumulator(), [], []
    if teacher is not None:  # warm-up: numba caches, hdbscan's worker pool
        teacher(pairs[0].pc0, pairs[0].pc1, pairs[0].ego1_from_ego0)
    for pair in pairs:
        if teacher is None:
            flow = ego_flow(pair.pc0, pair.ego1_from_ego0)
        else:
            extra = {"time0": pair.time0, "time1": pair.time1, "dt": pair.dt} if use_times else {}
            grounds = (pair.ground0, pair.ground1) if use_ground else (None, None)
            tic = time.perf_counter()
            flow = teacher(pair.pc0, pair.pc1, pair.ego1_from_ego0, *grounds, **extra).flow
            seconds.append(time.perf_counter() - tic)
        scores.add(metrics.frame_pair_stats(pair, flow, crop=crop))
        if pair.dynamic is not None:
            dynamic_errors.append(np.linalg.norm(flow - pair.flow, axis=1)[pair.dynamic])
    dynamic = float(np.concatenate(dynamic_errors).mean()) if dynamic_errors else float("nan")
    return scores.table()["point_weighted"], float(np.median(seconds)) if seconds else 0.0, dynamic


def print_table(title: str, rows: dict) -> None:
    print(f"\n{title}")
    columns = " | ".join(f"{c} EPE / Acc-S / Acc-R" for c in metrics.CATEGORIES[:3])
    print(f"| variant | s/pair | dynamic EPE (all) | {columns} |")
    print("|---|---|---|" + "---|" * 3)
    for name, (table, seconds, dynamic) in rows.items():
        cells = [
            f"{table[c]['EPE']:.4f} / {table[c]['AccS']:.4f} / {table[c]['AccR']:.4f}" for c in metrics.CATEGORIES[:3]
        ]
        print(f"| {name} | {seconds:.2f} | {dynamic:.4f} | " + " | ".join(cells) + " |")


def eval_av2(variants, ground: str, use_times: bool, base: dict) -> None:
    from icpflow.datasets.av2 import AV2Dataset

    pair = AV2Dataset(DATA / "av2", split="val", ground_threshold=0.4).pair(0)
    rows = {v: run_variant(VARIANTS[v], [pair], "av2", 51.2, ground == "map", use_times, base) for v in variants}
    print_table(
        f"AV2 pair {pair.sample_id} (preset av2 {base or ''}, ground: {ground}, per-point times: "
        f"{'yes' if use_times else 'no'}; {int(pair.dynamic.sum())} dynamic points)",
        rows,
    )


def eval_kitti(base: dict) -> None:
    data = np.load(SEQ01)
    poses = data["velo_poses_world"]
    teacher = ICPFlow(
        ICPFlowConfig.preset("waymo", ground={"method": "patchwork", "patchwork_z_offset": 0.0}, crop_xy=51.2, **base)
    )
    print("\nKITTI seq 01 (KISS-ICP + point-to-plane refinement; static = every non-car point)")
    print("| pair | ego dt (m) | ego drot (deg) | static flow EPE (m) | p95 (m) | s/pair |")
    print("|---|---|---|---|---|---|")
    for i in range(2):
        pc0, pc1 = data[f"points{i}"].astype(np.float32), data[f"points{i + 1}"].astype(np.float32)
        truth = relative_transform(poses[i], poses[i + 1])
        tic = time.perf_counter()
        result = teacher(pc0, pc1)
        seconds = time.perf_counter() - tic
        translation, angle = pose_error(result.ego1_from_ego0, truth)
        static = data[f"labels{i}"].reshape(-1) != 1
        error = np.linalg.norm(result.flow - ego_flow(pc0, truth), axis=1)[static]
        print(
            f"| {i}->{i + 1} | {translation:.4f} | {angle:.4f} | {error.mean():.4f} | "
            f"{np.quantile(error, 0.95):.4f} | {seconds:.2f} |"
        )


def eval_synthetic(variants, count: int, base: dict, split: str = "val") -> None:
    from icpflow.datasets.synthetic.reader import SyntheticDataset

    dataset = SyntheticDataset(split=split, num_sequences=max(1, -(-count // 4)))
    pairs = [dataset.pair(i) for i in range(min(count, len(dataset)))]
    rows = {v: run_variant(VARIANTS[v], pairs, "synthetic", 32.0, True, False, base) for v in variants}
    print_table(
        f"Synthetic {split}, {len(pairs)} pairs (conf/dataset/synthetic.yaml's teacher {base or ''}, the world's "
        "ground masks given unless the variant withholds them)",
        rows,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--av2", action="store_true")
    parser.add_argument("--av2-ground", choices=("map", "patchwork"), default="map")
    parser.add_argument("--no-times", action="store_true", help="AV2: do not pass per-point capture times")
    parser.add_argument("--kitti", action="store_true")
    parser.add_argument("--synthetic", type=int, default=0, help="number of synthetic pairs (0 = skip)")
    parser.add_argument("--split", default="val", help="the synthetic split")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="FIELD=VALUE",
        help="ICPFlowConfig overrides for every variant (values parsed as Python literals)",
    )
    args = parser.parse_args()
    variants = [v.strip() for v in args.variants.split(",")]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        parser.error(f"unknown variants {unknown}; choose from {list(VARIANTS)}")
    base = literal_overrides(args.set, parser, "--set")
    if args.av2:
        eval_av2(variants, args.av2_ground, not args.no_times, base)
    if args.kitti:
        eval_kitti(base)
    if args.synthetic:
        eval_synthetic(variants, args.synthetic, base, args.split)


if __name__ == "__main__":
    main()
