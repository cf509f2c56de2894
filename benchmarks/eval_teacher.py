"""Quality tables of the ICP-Flow teacher: Argoverse 2 pair, KITTI sequence 01 frames, synthetic val split.

    .venv/bin/python benchmarks/eval_teacher.py [--av2] [--kitti] [--synthetic N | --synthetic-seeds a:b]
        [--variants "teacher,centroid init,hungarian,kiss-icp ego,zero flow"]

Metrics per point group (the paper's table): EPE (m, mean end-point error), Acc-S (share of points with error
< 0.05 m or < 5 % of the ego-compensated ground-truth flow), Acc-R (< 0.1 m or < 10 %). Groups: dynamic (all),
dynamic fg, static fg, static bg (fg: points with a class / instance). Rows: the teacher (preset of the data set),
its ablations (centroid init, Hungarian, KISS-ICP ego motion) and the zero (ego-compensated) flow.
"""

from __future__ import annotations

import argparse
import ast
import time
from pathlib import Path

import numpy as np

from icpflow.geometry import ego_flow, invert, relative_transform
from icpflow.teacher import ICPFlow, ICPFlowConfig

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
VARIANTS = {
    "teacher": {},
    "centroid init": {"init": "centroid"},
    "hungarian": {"association": "hungarian"},
    "kiss-icp ego": {"ego_motion": "kiss_icp"},
    "zero flow": None,
}


def scores(flow: np.ndarray, pair) -> dict:
    """EPE / Acc-S / Acc-R per group of ``pair`` (a FramePair with flow, dynamic, classes or instance)."""
    error = np.linalg.norm(flow - pair.flow, axis=1)
    residual = np.linalg.norm(pair.flow - ego_flow(pair.pc0, pair.ego1_from_ego0), axis=1)
    relative = error / np.maximum(residual, 1e-6)
    valid = np.ones(len(error), bool) if pair.flow_valid is None else pair.flow_valid
    labels = pair.instance if pair.instance is not None else pair.classes
    fg = labels > 0 if labels is not None else np.zeros(len(error), bool)
    groups = {"dynamic": pair.dynamic, "dynamic fg": pair.dynamic & fg, "static fg": ~pair.dynamic & fg,
              "static bg": ~pair.dynamic & ~fg}  # fmt: skip
    out = {}
    for name, mask in groups.items():
        mask = mask & valid
        if mask.any():
            e, r = error[mask], relative[mask]
            out[name] = (e.mean(), ((e < 0.05) | (r < 0.05)).mean(), ((e < 0.1) | (r < 0.1)).mean(), int(mask.sum()))
    return out


def run_variant(name: str, pairs, preset: str, use_ground: bool, base: dict) -> tuple[dict, float]:
    """Per-group metrics pooled over ``pairs`` (point-weighted) and the median wall time per pair."""
    overrides = VARIANTS[name]
    sums: dict = {}
    times = []
    teacher = None if overrides is None else ICPFlow(ICPFlowConfig.preset(preset, **{**base, **overrides}))
    for pair in pairs:
        if teacher is None:
            flow = ego_flow(pair.pc0, pair.ego1_from_ego0)
        else:
            ego = None if overrides.get("ego_motion") == "kiss_icp" else pair.ego1_from_ego0
            grounds = (pair.ground0, pair.ground1) if use_ground else (None, None)
            tic = time.perf_counter()
            flow = teacher(pair.pc0, pair.pc1, ego, *grounds).flow
            times.append(time.perf_counter() - tic)
        for group, (epe, accs, accr, n) in scores(flow, pair).items():
            acc = sums.setdefault(group, np.zeros(4))
            acc += [epe * n, accs * n, accr * n, n]
    table = {g: (v[0] / v[3], v[1] / v[3], v[2] / v[3], int(v[3])) for g, v in sums.items()}
    return table, float(np.median(times)) if times else 0.0


def print_table(title: str, rows: dict) -> None:
    groups = ["dynamic", "dynamic fg", "static fg", "static bg"]
    print(f"\n{title}")
    print(f"| variant | s/pair | " + " | ".join(f"{g} EPE / Acc-S / Acc-R" for g in groups) + " |")
    print("|---|---|" + "---|" * len(groups))
    for name, (table, seconds) in rows.items():
        cells = [("%.3f / %.3f / %.3f" % table[g][:3]) if g in table else "-" for g in groups]
        print(f"| {name} | {seconds:.2f} | " + " | ".join(cells) + " |")


def eval_av2(variants, ground: str, base: dict) -> None:
    from icpflow.datasets.av2 import AV2Dataset

    root = DATA / "av2"
    threshold = 0.4 if ground == "map" else 0.3
    pair = AV2Dataset(root, split="val", ground_threshold=threshold).pair(0)
    rows = {v: run_variant(v, [pair], "av2", ground == "map", base) for v in variants}
    print_table(f"AV2 pair {pair.sample_id} (preset av2 {base or ''}, ground: {ground}; "
                f"{int(pair.dynamic.sum())} dynamic points)", rows)


def eval_kitti(cfg_overrides: dict) -> None:
    data = np.load(DATA / "kitti_odometry_seq01" / "kitti_odom_seq01_frames000-002_with_gt_poses.npz")
    poses = data["velo_poses_world"]
    teacher = ICPFlow(ICPFlowConfig.preset("waymo", ground="patchwork", patchwork_z_offset=0.0, crop_xy=51.2, **cfg_overrides))
    print("\nKITTI seq 01 (KISS-ICP + point-to-plane refinement; static = every non-car point)")
    print("| pair | ego dt (m) | ego drot (deg) | static flow EPE (m) | p95 (m) | s/pair |")
    print("|---|---|---|---|---|---|")
    for i in range(2):
        pc0, pc1 = data[f"points{i}"].astype(np.float32), data[f"points{i + 1}"].astype(np.float32)
        truth = relative_transform(poses[i], poses[i + 1])
        tic = time.perf_counter()
        result = teacher(pc0, pc1)
        seconds = time.perf_counter() - tic
        delta = invert(truth) @ result.ego1_from_ego0
        angle = np.degrees(np.arccos(np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1, 1)))
        static = data[f"labels{i}"].reshape(-1) != 1
        error = np.linalg.norm(result.flow - ego_flow(pc0, truth), axis=1)[static]
        print(f"| {i}->{i + 1} | {np.linalg.norm(delta[:3, 3]):.4f} | {angle:.4f} | {error.mean():.4f} | "
              f"{np.quantile(error, 0.95):.4f} | {seconds:.2f} |")


def synthetic_pairs(count: int, seeds: str | None) -> tuple[list, str]:
    """``count`` synthetic val pairs: from ``SyntheticDataset(split="val")``, or, with ``seeds`` "a:b", the pair
    (0, 1) of the worlds ``build_scene(seed)`` for seed in range(a, b) with the default 64-beam lidar."""
    if seeds:
        from icpflow.synthetic import Lidar, build_scene, sequence

        first, last = (int(v) for v in seeds.split(":"))
        pairs = [sequence(build_scene(seed), Lidar(), frames=[0, 1]).pair(0, 1) for seed in range(first, last)]
        return pairs, f"build_scene seeds {first}..{last - 1}"
    from icpflow.datasets.synthetic import SyntheticDataset

    dataset = SyntheticDataset(split="val")
    return [dataset.pair(i) for i in range(min(count, len(dataset)))], "SyntheticDataset(split='val')"


def eval_synthetic(variants, count: int, seeds: str | None, base: dict) -> None:
    pairs, source = synthetic_pairs(count, seeds)
    rows = {v: run_variant(v, pairs, "waymo", True, base) for v in variants}
    print_table(f"Synthetic {source}, {len(pairs)} pairs (preset waymo {base or ''}, ground masks given)", rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--av2", action="store_true")
    parser.add_argument("--av2-ground", choices=("map", "patchwork"), default="map")
    parser.add_argument("--kitti", action="store_true")
    parser.add_argument("--synthetic", type=int, default=0, help="number of val pairs (0 = skip)")
    parser.add_argument("--synthetic-seeds", default=None, help="a:b, worlds build_scene(a..b-1) instead of the split")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="ICPFlowConfig overrides for every variant (values parsed as Python literals)")
    args = parser.parse_args()
    variants = [v.strip() for v in args.variants.split(",")]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        parser.error(f"unknown variants {unknown}; choose from {list(VARIANTS)}")
    base = {key: ast.literal_eval(value) for key, value in (item.split("=", 1) for item in args.set)}
    if args.av2:
        eval_av2(variants, args.av2_ground, base)
    if args.kitti:
        eval_kitti({})
    if args.synthetic or args.synthetic_seeds:
        eval_synthetic(variants, args.synthetic, args.synthetic_seeds, base)


if __name__ == "__main__":
    main()
