"""Speed and agreement of the teacher's two ICP backends, ``icp.backend=cpu`` (numba, parallel over pairs) and
``icp.backend=torch`` (padded batch, ``torch.cdist``; CUDA whenever torch sees a GPU, else the CPU), on the
synthetic test pairs, with the teacher ``eval.py method=icpflow`` runs for ``dataset=synthetic``.

    .venv/bin/python -m benchmarks.teacher_backends [--pairs 32] [--teacher FIELD=VALUE ...] [--max-seconds S]
        [--json OUT] [--av2 ../shared/data/av2]

No Hydra: the reader is ``SyntheticDataset(split="test", ...)`` with conf/dataset/synthetic.yaml's ``reader``
settings (``num_sequences`` as many as ``--pairs`` needs: 4 pairs a sequence), the teacher
``ICPFlowConfig.preset(<the yaml's preset>)`` with the yaml's ``teacher`` block (as ``teacher_config`` builds it),
then the ``--teacher`` overrides (``ICPFlowConfig`` fields, values parsed as Python literals, e.g.
``--teacher icp.static_tolerance=0.0``) for both backends, then ``icp.backend``. Each backend's teacher runs once on
the first pair (warm-up: numba's kernels, CUDA's context and libraries, untimed), then the backends take turns on
every pair, called as ``teacher_on_sample`` calls it (ego motion, ground masks, point times, gap 1, dt); a line per
call goes to stderr. ``--max-seconds``: start no pair after S seconds of timed calls; the tables cover the pairs
done.

On the CPU the torch backend is slow: it pads every candidate pair of a stage to the stage's largest clusters
(``icp.max_points`` 10000 each) and runs ``torch.cdist`` over the padded batch every iteration (tens of minutes a
pair on 2 cores); ``--teacher icp.max_points=1000 --teacher icp.max_iter=10`` makes a quick check.

Prints two markdown tables:
1. per backend: the device ICP ran on, the warm-up call (s), the median seconds per pair (the teacher's call) and of
   its ICP stage (``result.timings["icp"]``), of which in the batch kernels (the median per pair of the seconds in
   ``registration.register_batch_torch`` and in ``register_batch_cpu``, timed by wrapping the module's names: the
   torch backend measures the identity's quality for ``icp.static_tolerance`` with a CPU pass), the median
   candidate pairs registered per teacher call, and the dynamic-foreground EPE (m) against the ground truth
   (eval.py's split: ``PairTruth.paper(dt, 32.0)``'s ``dynamic_fg``, non-ground points in the 64 m box moving
   faster than 0.5 m/s, class > 0; point-weighted over all pairs);
2. between the backends, over every pc0 point of every pair: the largest and the 99th percentile of
   ``|flow_cpu - flow_torch|`` (m), the share of points differing by more than 1 cm, and the share of pairs whose
   matched cluster pairs (``result.pairs``, as sets) are identical.
``--json OUT`` writes the same numbers, the per-pair figures, both configs and the environment (torch, CUDA, numba
threads).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import ROOT, literal_overrides

SYNTHETIC_YAML = ROOT / "conf" / "dataset" / "synthetic.yaml"
BACKENDS = ("cpu", "torch")
DIFF_TOLERANCE = 0.01  # m: a point whose two flows differ by more counts as differing


def dataset_settings() -> dict:
    """conf/dataset/synthetic.yaml as a dict, its interpolations resolved as Hydra resolves them (the teacher's ground
    block follows ``reader.sensor_height``; the split is the test split)."""
    from omegaconf import OmegaConf

    import icpflow.teacher.config  # noqa: F401  (registers the ``negative`` resolver)

    composed = OmegaConf.create({"split": "test", "dataset": OmegaConf.load(SYNTHETIC_YAML)})
    return OmegaConf.to_container(composed.dataset, resolve=True)


def reader_kwargs(settings: dict, pairs: int) -> dict:
    """``SyntheticDataset`` arguments of the yaml's ``reader`` (``_target_`` dropped) with enough test sequences for
    ``pairs`` pairs."""
    reader = {key: value for key, value in settings["reader"].items() if key != "_target_"}
    per_sequence = int(reader.get("frames_per_sequence", 5)) - int(reader.get("max_horizon", 1))
    reader["split"] = "test"
    reader["num_sequences"] = max(1, math.ceil(pairs / per_sequence))
    return reader


def teacher_configs(settings: dict, overrides: dict) -> dict:
    """{backend: ICPFlowConfig}: the dataset's preset with its ``teacher`` block (``teacher_config``'s order), then
    ``overrides``, then ``icp.backend``."""
    from icpflow.teacher.config import ICPFlowConfig

    base = ICPFlowConfig.preset(settings["preset"], **(settings.get("teacher") or {})).replace(**overrides)
    return {backend: base.replace(**{"icp.backend": backend}) for backend in BACKENDS}


class KernelClock:
    """Seconds spent in ``registration``'s batch kernels (``register_batch_torch``, ``register_batch_cpu``) since
    :meth:`reset`: the module's names are wrapped, nothing else changes. Both return numpy arrays, so a CUDA call
    has finished when it returns."""

    def __init__(self):
        from icpflow.teacher import registration

        self.seconds = dict.fromkeys(BACKENDS, 0.0)
        for backend, name in (("cpu", "register_batch_cpu"), ("torch", "register_batch_torch")):
            if hasattr(registration, name):
                setattr(registration, name, self._timed(backend, getattr(registration, name)))

    def _timed(self, backend, function):
        def timed(*args, **kwargs):
            tic = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                self.seconds[backend] += time.perf_counter() - tic

        return timed

    def reset(self) -> None:
        self.seconds = dict.fromkeys(BACKENDS, 0.0)


def torch_device() -> str:
    """The device ``registration_torch`` picks (it takes CUDA whenever torch sees a GPU), in words."""
    import torch

    if torch.cuda.is_available():
        return f"cuda: {torch.cuda.get_device_name(0)}"
    return f"cpu ({torch.get_num_threads()} threads)"


def call(teacher, pair):
    """The teacher on one pair as ``teacher_on_sample`` calls it (horizon 1)."""
    return teacher(
        pair.pc0,
        pair.pc1,
        ego1_from_ego0=pair.ego1_from_ego0,
        ground0=pair.ground0,
        ground1=pair.ground1,
        time0=pair.time0,
        time1=pair.time1,
        gap=1,
        dt=pair.dt,
    )


class BackendRun:
    """One backend's teacher and its per-pair figures, flows and matched cluster pairs."""

    def __init__(self, backend: str, cfg, clock: KernelClock):
        from icpflow.teacher import ICPFlow

        self.backend, self.teacher, self.clock = backend, ICPFlow(cfg), clock
        self.warmup_s = float("nan")
        self.figures = {"wall": [], "icp": [], "kernel_torch": [], "kernel_cpu": [], "candidates": []}
        self.flows, self.matches = [], []

    def warm_up(self, pair) -> None:
        """One untimed call (numba's kernels, CUDA's context and libraries), its seconds kept as ``warmup_s``."""
        tic = time.perf_counter()
        call(self.teacher, pair)
        self.warmup_s = time.perf_counter() - tic
        print(f"teacher_backends: {self.backend} warm-up {self.warmup_s:.1f} s", file=sys.stderr, flush=True)

    def run(self, pair, label: str) -> None:
        """One timed call, its figures appended (a line on stderr)."""
        self.clock.reset()
        tic = time.perf_counter()
        result = call(self.teacher, pair)
        wall = time.perf_counter() - tic
        figures = {
            "wall": wall,
            "icp": float(result.timings.get("icp", float("nan"))),
            "kernel_torch": self.clock.seconds["torch"],
            "kernel_cpu": self.clock.seconds["cpu"],
            "candidates": int(result.n_candidates),
        }
        for key, value in figures.items():
            self.figures[key].append(value)
        self.flows.append(np.asarray(result.flow, np.float64))
        self.matches.append({tuple(int(v) for v in row) for row in np.asarray(result.pairs).reshape(-1, 2)})
        print(
            f"teacher_backends: {label} {self.backend}: {wall:.2f} s, icp {figures['icp']:.2f} s (torch kernel "
            f"{figures['kernel_torch']:.2f}, cpu kernel {figures['kernel_cpu']:.2f}), {figures['candidates']} "
            f"candidates, {len(result.pairs)} matches",
            file=sys.stderr,
            flush=True,
        )


def dynamic_fg_epe(pairs, flows) -> tuple[float, int]:
    """Point-weighted EPE (m) over every pair's dynamic foreground (eval.py's split) and the points scored."""
    from icpflow.evaluation.metrics import PairTruth

    total, count = 0.0, 0
    for pair, flow in zip(pairs, flows):
        mask = PairTruth.of_pair(pair).paper(pair.dt, 32.0).masks["dynamic_fg"]
        epe = np.linalg.norm(flow[mask] - np.asarray(pair.flow, np.float64)[mask], axis=1)
        total, count = total + float(epe.sum()), count + int(mask.sum())
    return (total / count if count else float("nan")), count


def environment() -> dict:
    import numba
    import torch

    return {
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "cuda_available": torch.cuda.is_available(),
        "torch_device": torch_device(),
        "torch_threads": torch.get_num_threads(),
        "numba": numba.__version__,
        "numba_threads": numba.get_num_threads(),
    }


def report(numbers: dict) -> str:
    per, agree = numbers["backends"], numbers["agreement"]
    lines = [
        "| backend | device | warm-up (s) | s/pair (median) | ICP s (median) | in torch kernel / cpu kernel s (median) "
        "| candidates (median) | dynamic-fg EPE (m) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for backend in BACKENDS:
        row = per[backend]
        lines.append(
            f"| {backend} | {row['device']} | {row['warmup_s']:.2f} | {row['median_s_per_pair']:.3f} "
            f"| {row['median_icp_s']:.3f} | {row['median_kernel_torch_s']:.3f} / {row['median_kernel_cpu_s']:.3f} "
            f"| {row['median_candidates']:g} | {row['dynamic_fg_epe']:.4f} |"
        )
    lines += [
        "",
        "| max abs(flow_cpu - flow_torch) (m) | 99th percentile (m) | points differing > 1 cm | pairs with identical "
        "matches |",
        "| --- | --- | --- | --- |",
        f"| {agree['max_diff_m']:.3g} | {agree['p99_diff_m']:.3g} | {100 * agree['share_points_over_1cm']:.3f} % "
        f"| {agree['identical_match_pairs']}/{numbers['pairs']} ({100 * agree['share_identical_matches']:.0f} %) |",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=32, help="synthetic test pairs (4 per sequence; default 32)")
    parser.add_argument(
        "--teacher",
        action="append",
        default=[],
        metavar="FIELD=VALUE",
        help="an ICPFlowConfig override for both backends (repeatable; Python literals)",
    )
    parser.add_argument("--json", type=Path, default=None, metavar="OUT", help="write the numbers to this file")
    parser.add_argument(
        "--av2",
        type=Path,
        default=None,
        metavar="ROOT",
        help="the Argoverse 2 pair of ROOT (e.g. ../shared/data/av2: split val, pair 0, map ground within 0.3 m) with "
        "the av2 preset, instead of synthetic pairs",
    )
    parser.add_argument(
        "--max-seconds",
        type=float,
        default=None,
        metavar="S",
        help="start no pair after S seconds of timed calls (the table covers the pairs done)",
    )
    args = parser.parse_args(argv)
    if args.pairs < 1:
        parser.error("--pairs must be >= 1")
    overrides = literal_overrides(args.teacher, parser, "--teacher")
    if "icp.backend" in overrides or "icp_backend" in overrides:
        parser.error("--teacher: the backend is what this benchmark varies")

    from icpflow.datasets.synthetic.reader import SyntheticDataset
    from icpflow.teacher.warmup import ensure_compiled

    tic = time.perf_counter()
    if args.av2 is not None:
        from icpflow.datasets.av2 import AV2Dataset

        settings = {"preset": "av2", "teacher": {}}  # conf/dataset/av2.yaml's
        reader = {"root": str(args.av2), "split": "val", "ground_threshold": 0.3}
        pairs, what = [AV2Dataset(**reader).pair(0)], "Argoverse 2 pair (split val, pair 0, "
    else:
        settings = dataset_settings()
        reader = reader_kwargs(settings, args.pairs)
        dataset = SyntheticDataset(**reader)
        pairs = [dataset[i] for i in range(min(args.pairs, len(dataset)))]
        what = f"synthetic test pairs ({reader['num_sequences']} sequences, "
    configs = teacher_configs(settings, overrides)
    env = environment()
    print(
        f"teacher_backends: {len(pairs)} {what}"
        f"{np.mean([len(p.pc0) for p in pairs]):.0f} points per scan, made in {time.perf_counter() - tic:.1f} s); "
        f"preset {settings['preset']} + dataset teacher block; overrides {overrides or 'none'}; "
        f"torch {env['torch']} on {env['torch_device']}, numba {env['numba']} with {env['numba_threads']} threads",
        flush=True,
    )
    ensure_compiled("teacher_backends")
    clock = KernelClock()
    runs = {backend: BackendRun(backend, configs[backend], clock) for backend in BACKENDS}
    for run in runs.values():
        run.warm_up(pairs[0])
    started, done = time.perf_counter(), 0
    for index, pair in enumerate(pairs):
        if args.max_seconds is not None and time.perf_counter() - started > args.max_seconds:
            print(
                f"teacher_backends: --max-seconds {args.max_seconds:g} reached: {done} of {len(pairs)} pairs scored",
                file=sys.stderr,
                flush=True,
            )
            break
        for run in runs.values():  # the backends take turns on each pair
            run.run(pair, f"pair {index + 1}/{len(pairs)}")
        done += 1
    pairs = pairs[:done]

    backends = {}
    for backend, run in runs.items():
        epe, scored = dynamic_fg_epe(pairs, run.flows)
        backends[backend] = {
            "device": env["torch_device"] if backend == "torch" else f"cpu (numba, {env['numba_threads']} threads)",
            "warmup_s": run.warmup_s,
            "median_s_per_pair": statistics.median(run.figures["wall"]),
            "median_icp_s": statistics.median(run.figures["icp"]),
            "median_kernel_torch_s": statistics.median(run.figures["kernel_torch"]),
            "median_kernel_cpu_s": statistics.median(run.figures["kernel_cpu"]),
            "median_candidates": statistics.median(run.figures["candidates"]),
            "dynamic_fg_epe": epe,
            "dynamic_fg_points": scored,
            "per_pair": run.figures,
        }
    cpu, torch_run = runs["cpu"], runs["torch"]
    diffs = [np.linalg.norm(a - b, axis=1) for a, b in zip(cpu.flows, torch_run.flows)]
    every = np.concatenate(diffs)
    identical = [a == b for a, b in zip(cpu.matches, torch_run.matches)]
    numbers = {
        "pairs": len(pairs),
        "pairs_asked": args.pairs,
        "reader": reader,
        "teacher": {backend: cfg.to_dict() for backend, cfg in configs.items()},
        "overrides": overrides,
        "environment": env,
        "backends": backends,
        "agreement": {
            "max_diff_m": float(every.max(initial=0.0)),
            "p99_diff_m": float(np.percentile(every, 99)),
            "share_points_over_1cm": float((every > DIFF_TOLERANCE).mean()),
            "points": int(every.size),
            "identical_match_pairs": int(sum(identical)),
            "share_identical_matches": sum(identical) / len(pairs),
            "per_pair_max_diff_m": [float(d.max(initial=0.0)) for d in diffs],
            "per_pair_identical_matches": identical,
            "per_pair_matches": {backend: [len(m) for m in run.matches] for backend, run in runs.items()},
        },
    }
    print(report(numbers))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(numbers, indent=1, default=str) + "\n")
        print(f"teacher_backends: wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
