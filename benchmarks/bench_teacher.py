"""Wall time and peak memory of the ICP-Flow teacher per frame pair, with a per-stage breakdown.

    .venv/bin/python -m benchmarks.bench_teacher [--repeats 5] [--threads 2] [--kernels-only] [--set F=V ...]
        [--against F=V ...]

Rows (medians over ``repeats`` runs after one warm-up run):
* ``av2``: the Argoverse 2 pair in ../shared/data/av2 (2 x ~99k points), ego motion given (``ego_motion.npz``),
  per-point times from ``offset_ns`` (so the preset's de-skew step runs), preset "av2", ground from the teacher
  (Patchwork++).
* ``kitti``: KITTI HDL-64E scans 000000 -> 000001 in ../shared/data/kitti_hdl64_scans (~124k points each), no
  poses, so KISS-ICP estimates the ego motion; preset "av2" (Patchwork++ ground, 51.2 m crop).
* ``kernels``: the per-cluster kernels alone on P synthetic cluster pairs of ~300 points (car-sized box surfaces
  moved by up to 2 m and 0.3 rad): histogram initialisation and CPU ICP with checks.
Peak RSS is the process's maximum resident set size so far (``resource.getrusage``), so it is cumulative over rows.
``--against``: a second teacher (the same preset and ``--set``, then these overrides) timed side by side on the
av2 and kitti rows, the two alternating run by run; its rows are named ``case (against)`` and a last table gives
each case's time ratio (this teacher / the other).
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import statistics
import time

import numba
import numpy as np

from benchmarks.common import DATA, literal_overrides
from icpflow.core.geometry import make_transform, transform_points
from icpflow.teacher.checks import passes
from icpflow.teacher.config import ICPFlowConfig
from icpflow.teacher.histogram import initial_translations
from icpflow.teacher.pipeline import STAGES
from icpflow.teacher.registration import register_clusters


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def read_av2() -> tuple[np.ndarray, np.ndarray, np.ndarray, dict] | None:
    import pandas as pd

    logs = sorted((DATA / "av2" / "sensor" / "val").glob("*/"))
    if not logs:
        return None
    sweeps = sorted((logs[0] / "sensors" / "lidar").glob("*.feather"))[:2]
    frames = [pd.read_feather(s, columns=["x", "y", "z", "offset_ns"]) for s in sweeps]
    pc0, pc1 = (f[["x", "y", "z"]].to_numpy().astype(np.float32) for f in frames)
    time0, time1 = ((f["offset_ns"].to_numpy() * 1e-9).astype(np.float32) for f in frames)
    ego = np.load(logs[0] / "ego_motion.npz")["ego_motion"][0].astype(np.float64)
    dt = (int(sweeps[1].stem) - int(sweeps[0].stem)) * 1e-9
    return pc0, pc1, ego, {"time0": time0, "time1": time1, "dt": dt}


def read_kitti() -> tuple[np.ndarray, np.ndarray, None, dict] | None:
    scans = sorted((DATA / "kitti_hdl64_scans").glob("*.bin"))[:2]
    if len(scans) < 2:
        return None
    pc0, pc1 = (np.fromfile(s, dtype=np.float32).reshape(-1, 4)[:, :3].copy() for s in scans)
    return pc0, pc1, None, {}


def bench_teacher(name, data, configs: dict, repeats) -> list[dict]:
    """One row per teacher of ``configs`` (row name -> ICPFlowConfig) on one pair, their runs alternating."""
    from icpflow.teacher.pipeline import ICPFlow

    teachers = {row: ICPFlow(cfg) for row, cfg in configs.items()}
    pc0, pc1, ego, extra = data
    for teacher in teachers.values():
        teacher(pc0, pc1, ego, **extra)  # warm-up: numba caches, Patchwork++ and KISS-ICP objects
    walls = {row: [] for row in teachers}
    stages = {row: {s: [] for s in STAGES} for row in teachers}
    results = {}
    for _ in range(repeats):
        for row, teacher in teachers.items():
            tic = time.perf_counter()
            results[row] = teacher(pc0, pc1, ego, **extra)
            walls[row].append(time.perf_counter() - tic)
            for s in STAGES:
                stages[row][s].append(results[row].timings.get(s, 0.0))
    rows = []
    for row in teachers:
        out = {"case": row, "points": f"{len(pc0)}+{len(pc1)}", "total": statistics.median(walls[row])}
        out.update({s: statistics.median(v) for s, v in stages[row].items()})
        out.update(candidates=results[row].n_candidates, matches=len(results[row].pairs), rss=peak_rss_mb())
        rows.append(out)
    return rows


def synthetic_pairs(count: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    size = np.array([4.4, 1.8, 1.5])
    pairs = []
    for _ in range(count):
        n = int(rng.integers(250, 350))
        points = rng.uniform(-size / 2, size / 2, (n, 3))
        axis = rng.integers(0, 3, n)
        points[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -1, 1) * size[axis] / 2
        motion = make_transform(rng.uniform(-0.3, 0.3), (*rng.uniform(-2, 2, 2), 0.0))
        moved = transform_points(motion, points) + rng.normal(0, 0.02, points.shape)
        pairs.append((points.astype(np.float32), moved.astype(np.float32)))
    return pairs


def bench_kernels(count, cfg, repeats) -> dict:
    pairs = synthetic_pairs(count)
    windows = np.full(count, cfg.pairing.window(0.0))

    def run():
        tic = time.perf_counter()
        translations, _ = initial_translations(pairs, windows, cfg.histogram, cfg.seed)
        mid = time.perf_counter()
        inits = np.tile(np.eye(4), (count, 1, 1))
        inits[:, :3, 3] = translations
        result = register_clusters(pairs, inits, dataclasses.replace(cfg.icp, backend="cpu"), cfg.seed)
        centroids = np.array([p[0].mean(axis=0) for p in pairs])
        passes(result.transforms, result.mean_error, result.iou_ratio, windows, cfg.checks, src_centroids=centroids)
        return mid - tic, time.perf_counter() - mid

    run()
    times = [run() for _ in range(repeats)]
    hist, icp = statistics.median(t[0] for t in times), statistics.median(t[1] for t in times)
    row = {"case": f"kernels P={count}", "points": f"{count} x ~300", "total": hist + icp}
    row.update({s: float("nan") for s in STAGES})
    row.update(histogram=hist, icp=icp, candidates=count, matches=0, rss=peak_rss_mb())
    return row


def print_table(rows) -> None:
    head = ["case", "points", "total s", *STAGES, "candidates", "matches", "peak RSS MB"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        cells = [r["case"], r["points"], f"{r['total']:.3f}"]
        cells += ["-" if r[s] != r[s] else f"{r[s]:.3f}" for s in STAGES]
        cells += [str(r["candidates"]), str(r["matches"]), f"{r['rss']:.0f}"]
        print("| " + " | ".join(cells) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2, help="numba threads")
    parser.add_argument("--pairs", type=int, default=200, help="cluster pairs in the kernels-only row")
    parser.add_argument("--kernels-only", action="store_true")
    parser.add_argument(
        "--against",
        nargs="*",
        default=None,
        metavar="FIELD=VALUE",
        help="a second teacher: the same config with these overrides, timed side by side",
    )
    parser.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="FIELD=VALUE",
        help="ICPFlowConfig overrides of the av2 preset, e.g. icp.backend='torch' (values parsed as Python literals)",
    )
    args = parser.parse_args()
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))

    cfg = ICPFlowConfig.preset("av2", **literal_overrides(args.set, parser, "--set"))
    rows = [bench_kernels(args.pairs, cfg, args.repeats)]
    if not args.kernels_only:
        for name, reader in (("av2", read_av2), ("kitti", read_kitti)):
            data = reader()
            if data is None:
                print(f"skipped {name}: no data under {DATA}")
                continue
            configs = {name: cfg}
            if args.against is not None:
                configs[f"{name} (against)"] = cfg.replace(**literal_overrides(args.against, parser, "--against"))
            rows += bench_teacher(name, data, configs, args.repeats)
    print(f"numba threads {numba.get_num_threads()}, median of {args.repeats} after a warm-up; seconds")
    print_table(rows)
    if args.against is not None:
        totals = {r["case"]: r["total"] for r in rows}
        print(f"\nTime ratio, this teacher / the one with {' '.join(args.against)}")
        print("| case | ratio |\n|---|---|")
        for case in [c for c in totals if f"{c} (against)" in totals]:
            print(f"| {case} | {totals[case] / totals[f'{case} (against)']:.3f} |")


if __name__ == "__main__":
    main()
