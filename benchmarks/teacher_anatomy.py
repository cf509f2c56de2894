"""Where the teacher's dynamic error is, per moving object, and why: the per-extent table and a diagnosis of every
moving object through the teacher's steps (issue 30).

    .venv/bin/python -m benchmarks.teacher_anatomy [--set split=test --set dataset.reader.num_sequences=8]
        [--teacher FIELD=VALUE ...] [--objects 8] [--list 20]

``--set``: ``eval.py`` overrides choosing the split (any dataset with ground-truth flow and pc0 instance ids; the
synthetic test split of 8 sequences = 32 pairs by default); ``--teacher``: ``ICPFlowConfig`` overrides over the
dataset's teacher (values parsed as Python literals, e.g. ``--teacher clustering.epsilon=0.5``). Points scored are
``eval.py``'s dynamic foreground (non-ground, in the dataset's crop, true residual speed > 0.5 m/s, class > 0);
objects are the instances with >= 5 such points, their extent the length of their pc0 points along the main
horizontal axis.

Prints:
1. per extent: objects, share of moving points, share of the teacher's summed EPE, EPE (m), median speed (m/s),
   and the dynamic EPE without that extent;
2. for objects of at least ``--objects`` metres, and for all objects, the FIRST step that went wrong, in the
   pipeline's order, with objects, share of their points, share of their summed EPE and their EPE:
   ``noise`` (over half the object's points in no cluster), ``split`` (two clusters hold >= 15 % each),
   ``merged`` (its main cluster is >= 20 % other objects' or background points), ``not paired`` (the main cluster
   and the one holding the object's points in pc1 were never a candidate pair), ``checks`` (that pair was
   registered and failed the checks), ``association`` (it passed and another partner was chosen), ``no match``
   (nothing chosen for the main cluster), ``start`` (the chosen pair's start translation is > 0.5 m from the
   true one), ``slide`` (the registered motion's error at the object's centroid is > 0.2 m and mostly along the
   object's main axis), ``rotation`` (yaw error > 1 degree), ``other`` (EPE > 0.2 m, none of the above),
   ``ok``;
3. the ``--list`` worst objects (summed EPE) with their figures.
The true motion of an object is the rigid fit (``geometry.kabsch``) of its ego-compensated pc0 points onto
pc0 + the true flow, in pc1's frame (the teacher's registration frame).
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from types import SimpleNamespace

import numpy as np
from scipy.spatial import cKDTree

from benchmarks.common import literal_overrides, open_split
from icpflow.geometry import euler_angles, kabsch, transform_points
from icpflow.metrics import PairTruth
from icpflow.teacher.histogram import main_axis

EXTENT_BINS = (0.0, 2.0, 5.0, 8.0, 20.0)  # m
MIN_OBJECT_POINTS = 5
CAUSES = (
    "noise",
    "split",
    "merged",
    "not paired",
    "checks",
    "association",
    "no match",
    "start",
    "slide",
    "rotation",
    "other",
    "ok",
)


def share_of(labels: np.ndarray) -> Counter:
    """Counts of each label >= 0 in ``labels``."""
    return Counter(int(v) for v in labels[labels >= 0])


def diagnose(pair, result, dynamic: np.ndarray) -> list[dict]:
    """One record per moving object of ``pair`` (instances with >= ``MIN_OBJECT_POINTS`` dynamic points): its
    extent, speed, points, summed and mean EPE over ``dynamic`` and the first step that went wrong (``CAUSES``)."""
    ego = result.ego1_from_ego0
    error = np.linalg.norm(result.flow - pair.flow, axis=1)
    pc1_tree = cKDTree(pair.pc1)
    candidates = result.candidates
    tried = {(int(s), int(d)): k for k, (s, d) in enumerate(zip(candidates["src"], candidates["dst"]))}
    non_ground = ~result.ground0
    records = []
    for instance in np.unique(pair.instance[dynamic]):
        members = dynamic & (pair.instance == instance)
        if members.sum() < MIN_OBJECT_POINTS:
            continue
        obj = pair.instance == instance
        axis, extent = main_axis(pair.pc0[obj].astype(np.float64))
        src = transform_points(ego, pair.pc0[members].astype(np.float64))
        dst = pair.pc0[members].astype(np.float64) + pair.flow[members]
        truth = kabsch(src, dst)
        centroid = src.mean(axis=0)
        true_shift = transform_points(truth, centroid[None])[0] - centroid
        record = {
            "id": f"{pair.sample_id}#{int(instance)}",
            "extent": extent,
            "speed": float(np.linalg.norm(true_shift[:2]) / pair.dt),
            "points": int(members.sum()),
            "summed": float(error[members].sum()),
            "epe": float(error[members].mean()),
        }
        labels = result.labels0[members]
        counts = share_of(labels)
        n = int(members.sum())
        main = counts.most_common(1)[0][0] if counts else -1
        record["clusters"] = sum(1 for c in counts.values() if c >= 0.15 * n)
        scene = SimpleNamespace(result=result, non_ground=non_ground, pc1_tree=pc1_tree, tried=tried)
        moving = SimpleNamespace(
            n=n, counts=counts, main=main, mask=obj, moved=dst, truth=truth, centroid=centroid, shift=true_shift
        )
        record["cause"] = _first_cause(record, moving, scene, axis)
        records.append(record)
    return records


def _first_cause(record: dict, obj: SimpleNamespace, scene: SimpleNamespace, axis: np.ndarray) -> str:
    """The first step that went wrong for one moving object (``CAUSES``); fills the record's start error, along /
    across error and yaw error where its main cluster has a match to the right partner. ``obj``: the object's
    dynamic points (``n``, label ``counts``, ``main`` label, pc0 ``mask`` of all its points, ``moved`` points at
    pc0 + true flow, true motion ``truth``, ``centroid``, true centroid ``shift``); ``scene``: the teacher's
    ``result``, pc0's ``non_ground`` mask, ``pc1_tree`` (a cKDTree of pc1), ``tried`` ((src, dst) -> candidate row)."""
    result, candidates = scene.result, scene.result.candidates
    n, counts, main, true_shift, centroid = obj.n, obj.counts, obj.main, obj.shift, obj.centroid
    if sum(counts.values()) < 0.5 * n:
        return "noise"
    if record["clusters"] >= 2:
        return "split"
    in_main = (result.labels0 == main) & scene.non_ground
    if (in_main & ~obj.mask).sum() >= 0.2 * in_main.sum():
        return "merged"
    distance, nearest = scene.pc1_tree.query(obj.moved, distance_upper_bound=0.3)
    hit = nearest[np.isfinite(distance)]
    dst_counts = share_of(result.labels1[hit]) if len(hit) else Counter()
    partner = dst_counts.most_common(1)[0][0] if dst_counts else -1
    k_true = scene.tried.get((main, partner))
    rows = np.flatnonzero(result.pairs[:, 0] == main)
    if len(rows) == 0:
        if k_true is None:
            return "not paired" if partner >= 0 else "no match"
        return "no match" if candidates["passed"][k_true] else "checks"
    row = rows[0]
    if int(result.pairs[row, 1]) != partner:
        if k_true is None:
            return "not paired"
        return "association" if candidates["passed"][k_true] else "checks"
    merged = int(result.stage[row]) == 3  # registered as one by the merging step: no stage-1/2 start
    start_error = np.nan if merged or k_true is None else np.linalg.norm(candidates["init"][k_true] - true_shift)
    transform = result.transforms[row]
    moved = transform_points(transform, centroid[None])[0] - centroid
    miss = moved - true_shift
    along = abs(float(miss[:2] @ axis))
    across = float(np.linalg.norm(miss - np.r_[axis * (miss[:2] @ axis), 0.0]))
    yaw_error = abs(np.degrees(euler_angles(transform)[2] - euler_angles(obj.truth)[2]))
    record["start_error"], record["along"], record["across"], record["yaw_error"] = (
        float(start_error),
        along,
        across,
        float(yaw_error),
    )
    if record["epe"] <= 0.2:
        return "ok"
    if start_error > 0.5:  # NaN (merged) compares False
        return "start"
    if np.hypot(along, across) > 0.2 and along > 2 * across:
        return "slide"
    if yaw_error > 1.0:
        return "rotation"
    return "other"


def report(records: list[dict], long_from: float, listed: int) -> str:
    extent = np.array([r["extent"] for r in records])
    points = np.array([r["points"] for r in records], float)
    summed = np.array([r["summed"] for r in records])
    speed = np.array([r["speed"] for r in records])
    lines = [
        f"{len(records)} moving objects, {int(points.sum())} dynamic points, dynamic EPE "
        f"{summed.sum() / points.sum():.3f} m",
        "",
    ]
    lines.append(
        "| extent | objects | share of moving points | share of summed EPE | teacher EPE (m) | median speed "
        "(m/s) | dynamic EPE without them |"
    )
    lines.append("|---|---|---|---|---|---|---|")
    for low, high in zip(EXTENT_BINS[:-1], EXTENT_BINS[1:]):
        pick = (extent >= low) & (extent < high)
        if not pick.any():
            continue
        rest = summed[~pick].sum() / max(points[~pick].sum(), 1)
        lines.append(
            f"| {low:g}-{high:g} m | {pick.sum()} | {points[pick].sum() / points.sum():.0%} | "
            f"{summed[pick].sum() / summed.sum():.0%} | {summed[pick].sum() / points[pick].sum():.3f} | "
            f"{np.median(speed[pick]):.1f} | {rest:.3f} |"
        )
    for title, pick in ((f">= {long_from:g} m", extent >= long_from), ("all", np.ones(len(records), bool))):
        if not pick.any():
            continue
        causes = np.array([r["cause"] for r in records])
        lines += ["", f"First step that went wrong, objects {title} ({pick.sum()})", ""]
        lines.append("| cause | objects | share of their points | share of their summed EPE | EPE (m) |")
        lines.append("|---|---|---|---|---|")
        for cause in CAUSES:
            mask = pick & (causes == cause)
            if mask.any():
                lines.append(
                    f"| {cause} | {mask.sum()} | {points[mask].sum() / points[pick].sum():.0%} | "
                    f"{summed[mask].sum() / summed[pick].sum():.0%} | {summed[mask].sum() / points[mask].sum():.3f} |"
                )
    if listed:
        lines += ["", f"The {listed} worst objects (summed EPE)", ""]
        lines.append(
            "| object | extent (m) | speed (m/s) | points | EPE (m) | clusters | cause | start error | "
            "along / across (m) | yaw error (deg) |"
        )
        lines.append("|---|---|---|---|---|---|---|---|---|---|")
        for r in sorted(records, key=lambda r: -r["summed"])[:listed]:
            fit = (
                f"{r['start_error']:.2f} | {r['along']:.2f} / {r['across']:.2f} | {r['yaw_error']:.2f}"
                if "along" in r
                else "- | - | -"
            )
            lines.append(
                f"| {r['id']} | {r['extent']:.1f} | {r['speed']:.1f} | {r['points']} | {r['epe']:.3f} | "
                f"{r['clusters']} | {r['cause']} | {fit} |"
            )
    return "\n".join(lines)


def main() -> None:
    from icpflow.teacher import ICPFlow
    from icpflow.teacher.config import teacher_config

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--set", action="append", default=[], help="an eval.py override (repeatable)")
    parser.add_argument(
        "--teacher",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="an ICPFlowConfig override over the dataset's teacher (repeatable)",
    )
    parser.add_argument("--objects", type=float, default=8.0, help="extent (m) from which objects count as long")
    parser.add_argument("--list", type=int, default=20, help="worst objects to list")
    args = parser.parse_args()
    overrides = args.set or ["split=test", "dataset.reader.num_sequences=8"]
    dataset, cfg = open_split(overrides)
    fields = literal_overrides(args.teacher, parser, "--teacher")
    teacher = ICPFlow(teacher_config(cfg).replace(**fields))
    records, seconds = [], []
    for index in range(len(dataset)):
        pair = dataset[index]
        if pair.instance is None or pair.flow is None:
            raise SystemExit(f"{pair.source}: the anatomy needs ground-truth flow and instance ids")
        tic = time.perf_counter()
        result = teacher(
            pair.pc0, pair.pc1, pair.ego1_from_ego0, pair.ground0, pair.ground1, gap=1, dt=pair.dt, candidates=True
        )
        seconds.append(time.perf_counter() - tic)
        dynamic = PairTruth.of_pair(pair).paper(pair.dt, cfg.crop).masks["dynamic_fg"]
        records += diagnose(pair, result, dynamic)
    print(
        f"eval.py {' '.join(overrides)}: {len(dataset)} pairs; teacher overrides {fields or 'none'}; "
        f"median {np.median(seconds):.2f} s/pair"
    )
    print(report(records, args.objects, args.list))


if __name__ == "__main__":
    main()
