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

On real pairs (``--kitti00 [VARIANT]``: the KITTI 00 pairs of ``benchmarks.teacher_real_pairs``, which hold exact
static flow and labelled movers but no movers' flow) the failing objects are of two kinds, each given the first step
that went wrong (:func:`diagnose_real`):
- a teacher cluster whose static points (labelled ground left out) are more than :data:`FALSE_MOTION_M` off their
  exact flow: ``ground`` (half its points are labelled ground: the ground step left them), ``cluster`` (a fifth are
  labelled movers: merged with one), ``ego motion`` (no match: the ego motion alone is off), ``pairing`` (matched to
  a cluster other than the one its points truly land in, the true pair never a candidate), ``checks`` (the true
  pair was a candidate and failed the checks), ``association`` (it passed, the wrong one was chosen), ``vote`` (the
  right partner, the start translation more than 0.3 m from the truth), ``ICP`` (the right partner and a good
  start, the registration slid and the checks and the static test let it through);
- a labelled mover (an instance of >= ``MIN_OBJECT_POINTS`` moving points) of which under half move by more than
  ``teacher_real_pairs.MOVING_M``: ``ground``, ``noise`` (half its points in no cluster: fewer than the clustering's
  minimum, or cropped), ``cluster`` (its cluster is mostly static points), ``not paired`` (no candidate pair),
  ``checks`` (no candidate passed), ``static test`` (the match kept the identity: ``pipeline._prefer_static``),
  ``ICP`` (matched and moved too little).
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from types import SimpleNamespace

import numpy as np
from scipy.spatial import cKDTree

from benchmarks.common import literal_overrides, open_split
from icpflow.core.geometry import ego_flow, euler_angles, kabsch, transform_points
from icpflow.evaluation.metrics import PairTruth
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
#: residual (m) of a static cluster's points above which it is a failing object on real pairs
FALSE_MOTION_M = 0.05
STATIC_CAUSES = ("ground", "cluster", "ego motion", "pairing", "checks", "association", "vote", "ICP")
MOVER_CAUSES = ("ground", "noise", "cluster", "not paired", "checks", "static test", "ICP")


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


def _true_partner(result, tree: cKDTree, landed: np.ndarray) -> int:
    """The pc1 cluster most of ``landed`` (points at their true place in pc1) fall on within 0.3 m (-1: none)."""
    distance, nearest = tree.query(landed, distance_upper_bound=0.3)
    counts = share_of(result.labels1[nearest[np.isfinite(distance)]])
    return counts.most_common(1)[0][0] if counts else -1


def _static_cause(pair: dict, result, cluster: int, tree: cKDTree) -> dict:
    """The first step that went wrong for a teacher cluster of ``pair`` (``teacher_real_pairs.read_pair``) whose
    static points moved (``STATIC_CAUSES``), with its match's figures."""
    members = result.labels0 == cluster
    record = {"kind": "static", "id": f"{pair['name']}#{cluster}", "points": int(members.sum())}
    if pair["ground0"][members].mean() >= 0.5:
        return record | {"cause": "ground"}
    if pair["moving0"][members].mean() >= 0.2:
        return record | {"cause": "cluster"}
    rows = np.flatnonzero(result.pairs[:, 0] == cluster)
    if len(rows) == 0:
        return record | {"cause": "ego motion"}
    ego = result.ego1_from_ego0
    src = transform_points(ego, pair["pc0"][members].astype(np.float64))  # the teacher's registration frame
    landed = transform_points(pair["ego1_from_ego0"], pair["pc0"][members].astype(np.float64))
    centroid = src.mean(axis=0)
    true_shift = landed.mean(axis=0) - centroid
    transform = result.transforms[rows[0]]
    record["moved"] = float(np.linalg.norm(transform_points(transform, centroid[None])[0] - centroid - true_shift))
    record["iou"] = float(result.iou_ratios[rows[0]])
    partner, chosen = _true_partner(result, tree, landed), int(result.pairs[rows[0], 1])
    candidates = result.candidates
    tried = np.flatnonzero((candidates["src"] == cluster) & (candidates["dst"] == partner))
    if chosen != partner:
        if len(tried) == 0:
            return record | {"cause": "pairing"}
        return record | {"cause": "association" if candidates["passed"][tried].any() else "checks"}
    k = np.flatnonzero((candidates["src"] == cluster) & (candidates["dst"] == chosen) & candidates["chosen"])
    start = candidates["init"][k[0]] if len(k) and int(result.stage[rows[0]]) != 3 else None
    if start is not None and np.linalg.norm(start - true_shift) > 0.3:
        return record | {"cause": "vote"}
    return record | {"cause": "ICP"}


def _mover_cause(pair: dict, result, members: np.ndarray) -> str:
    """The first step that went wrong for a labelled mover (``members``: its pc0 points) that the teacher left
    static (``MOVER_CAUSES``)."""
    if result.ground0[members].mean() >= 0.5:
        return "ground"
    counts = share_of(result.labels0[members])
    if sum(counts.values()) < 0.5 * members.sum():
        return "noise"
    main = counts.most_common(1)[0][0]
    in_main = result.labels0 == main
    if (in_main & ~pair["moving0"]).sum() >= 0.5 * in_main.sum():
        return "cluster"
    candidates = result.candidates
    tried = candidates["src"] == main
    if not tried.any():
        return "not paired"
    if not candidates["passed"][tried].any():
        return "checks"
    chosen = np.flatnonzero(tried & candidates["chosen"])
    if len(chosen) and np.allclose(candidates["transforms"][chosen[0]], np.eye(4)):
        return "static test"
    return "ICP"


def diagnose_real(pair: dict, result) -> list[dict]:
    """The failing objects of one real pair (``teacher_real_pairs.read_pair``) under the teacher's ``result`` (with
    its candidates): static clusters moved by more than ``FALSE_MOTION_M`` and labelled movers left static, each with
    its kind, id, points, residual (the static points' mean residual, or the movers' share found) and cause."""
    from benchmarks.teacher_real_pairs import MOVING_M

    truth = ego_flow(pair["pc0"], pair["ego1_from_ego0"])
    residual = np.linalg.norm(result.flow - truth, axis=1)
    scored = ~pair["moving0"] & ~pair["ground0"]
    tree = cKDTree(pair["pc1"])
    records = []
    for cluster in np.unique(result.labels0[result.labels0 >= 0]):
        members = (result.labels0 == cluster) & scored
        if members.any() and residual[members].mean() > FALSE_MOTION_M:
            record = _static_cause(pair, result, int(cluster), tree)
            records.append(record | {"residual": float(residual[members].mean())})
    instances = pair["instance0"]
    for instance in np.unique(instances[pair["moving0"]]):
        members = pair["moving0"] & (instances == instance)
        found = float((residual[members] > MOVING_M).mean())
        if members.sum() >= MIN_OBJECT_POINTS and found < 0.5:
            record = {"kind": "mover", "id": f"{pair['name']}#{int(instance)}", "points": int(members.sum())}
            records.append(record | {"residual": found, "cause": _mover_cause(pair, result, members)})
    return records


def report_real(records: list[dict], pairs: int) -> str:
    """The failing objects of ``pairs`` real pairs: per kind, the objects and points per cause, then each object."""
    lines = []
    for kind, causes, title in (
        ("static", STATIC_CAUSES, "static clusters moved (residual over 5 cm)"),
        ("mover", MOVER_CAUSES, "labelled movers left static"),
    ):
        picked = [r for r in records if r["kind"] == kind]
        lines += ["", f"{len(picked)} {title} in {pairs} pairs", "", "| cause | objects | points |", "|---|---|---|"]
        for cause in causes:
            chosen = [r for r in picked if r["cause"] == cause]
            if chosen:
                lines.append(f"| {cause} | {len(chosen)} | {sum(r['points'] for r in chosen)} |")
    lines += [
        "",
        "| object | kind | points | static residual (m) or movers found | cause | match off the truth (m) | IoU |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in sorted(records, key=lambda r: (r["kind"], -r["residual"] * r["points"])):
        match = f"{r['moved']:.3f} | {r['iou']:.2f}" if "moved" in r else "- | -"
        lines.append(f"| {r['id']} | {r['kind']} | {r['points']} | {r['residual']:.3f} | {r['cause']} | {match} |")
    return "\n".join(lines)


def main_real(variant: str, fields: dict, count: int) -> None:
    """``--kitti00``: the failing objects of the real KITTI 00 pairs under one ``teacher_real_pairs`` variant."""
    from benchmarks.eval_teacher import dataset_teacher
    from benchmarks.teacher_real_pairs import PAIRS, read_pair, variant_inputs
    from icpflow.teacher import ICPFlow

    files = sorted(PAIRS.glob("*.npz"))[:count]
    if not files:
        raise SystemExit(f"teacher_anatomy: no pairs in {PAIRS}")
    teacher = ICPFlow(dataset_teacher("kitti", fields))
    records = []
    for path in files:
        pair, inputs = variant_inputs(read_pair(path), variant)
        records += diagnose_real(pair, teacher(*inputs, candidates=True))
    print(f"KITTI 00 pairs: {len(files)}, variant {variant!r}; teacher overrides {fields or 'none'}")
    print(report_real(records, len(files)))


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
    parser.add_argument(
        "--kitti00",
        nargs="?",
        const="given",
        metavar="VARIANT",
        help="the failing objects of the real KITTI 00 pairs instead, under a teacher_real_pairs variant (given)",
    )
    parser.add_argument("--pairs", type=int, default=30, help="real pairs with --kitti00")
    args = parser.parse_args()
    if args.kitti00:
        return main_real(args.kitti00, literal_overrides(args.teacher, parser, "--teacher"), args.pairs)
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
