"""Streaming inference (``fastflow3d.inference.stream.FlowStream``): per-frame latency on real scans.

    .venv/bin/python benchmarks/bench_stream.py latency [--backends onnx-tuned,openvino] [--scans kitti,av2]
        [--passes 5] [--threads 2] [--model fastflow3d_small] [--regimes pairwise,streamed,given] [--device cpu|cuda]

``latency``: each scan list is played as a stream (KITTI HDL-64E ``000000``-``000005``; the two AV2 sweeps
alternate, s0 s1 s0 s1 ..., as the only AV2 stream shipped) ``--passes`` times from a fresh stream; the frames after
the first two of each pass are timed (the whole ``push``). Regimes: ``pairwise`` (``Predictor.predict`` on each pair
with nothing given: today's path), ``streamed`` (nothing given) and ``given`` (the ego motion and ground masks passed
in, computed beforehand). The model has random weights (latency does not depend on them); ``--backends`` are
``bench_latency.py``'s (``onnx-tuned`` and ``openvino``: ``fastflow3d.artifact.engines``, the CPU engines; ``eager``,
``eager-bf16``, ``compile``: PyTorch on ``--device``; ``onnx``: ONNX Runtime's CUDA provider with ``--device cuda``
where ``onnxruntime-gpu`` is installed, else its CPU provider). With ``--device cuda`` only the network runs on the
GPU: ground, odometry and the rest stay on the CPU's ``--threads``. Prints median / p90 ms, Hz, the RSS growth of the
stream (and the GPU's peak memory), and the streamed regime's time per step (ground, odometry, network, the rest).

The ego motion's error against true poses, streamed and pairwise: ``benchmarks/bench_ego_motion.py``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from bench_latency import (  # benchmarks/ is the script's folder
    BACKENDS,
    DATA,
    TEACHERS,
    build_network,
    cpu_name,
    export_formats,
    model_config,
    rss_mb,
)

from fastflow3d.artifact.checkpoint import build_student
from fastflow3d.artifact.export import export_model
from fastflow3d.inference.predictor import Predictor
from fastflow3d.inference.stream import FlowStream
from fastflow3d.network.contract import InputContract
from icpflow.preprocess import Preprocessing, lift_points

REGIMES = ("pairwise", "streamed", "given")


def stream_scans(name: str) -> list[np.ndarray] | None:
    """The scans of a shipped stream, in order (the AV2 sweeps alternating), or None where they are absent."""
    if name == "kitti":
        files = sorted((DATA / "kitti_hdl64_scans").glob("*.bin"))
        return [np.fromfile(f, np.float32).reshape(-1, 4)[:, :3].copy() for f in files] or None
    import pandas as pd

    sweeps = sorted((DATA / "av2" / "sensor" / "val").glob("*/sensors/lidar/*.feather"))
    scans = [pd.read_feather(s, columns=["x", "y", "z"]).to_numpy().astype(np.float32) for s in sweeps]
    return [scans[i % len(scans)] for i in range(6)] if len(scans) >= 2 else None


class StepClock:
    """Seconds spent in the stream's steps (ground, odometry, network), by wrapping the callables it calls."""

    def __init__(self, stream: FlowStream):
        self.spent = {"ground (1 scan)": 0.0, "odometry (a step)": 0.0, "network": 0.0}
        predictor = stream.predictor
        predictor.scan_masks = self.wrap(predictor.scan_masks, "ground (1 scan)")
        stream.odometry.step = self.wrap(stream.odometry.step, "odometry (a step)")
        predictor.network = self.wrap(predictor.network, "network")

    def wrap(self, function, key):
        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                self.spent[key] += time.perf_counter() - start

        return timed

    def take(self) -> dict[str, float]:
        spent, self.spent = self.spent, dict.fromkeys(self.spent, 0.0)
        return spent


def latency(args) -> None:
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    regimes = [r.strip() for r in args.regimes.split(",") if r.strip()]
    unknown = sorted(set(backends) - set(BACKENDS)) + sorted(set(regimes) - set(REGIMES))
    if unknown or not backends or not regimes:
        raise SystemExit(f"bench_stream: unknown {', '.join(unknown) or '(none)'}; backends {BACKENDS}, {REGIMES}")
    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("bench_stream: --device cuda but torch sees no CUDA device (a CPU build of torch?)")
    torch.set_num_threads(args.threads)
    model = build_student(model_config(args.model, [])).eval()
    gpu = f", {torch.cuda.get_device_name()}, torch {torch.__version__}" if args.device == "cuda" else ""
    print(
        f"model {args.model} grid {model.grid.nx}x{model.grid.ny}; network on {args.device}{gpu}; {cpu_name()}, "
        f"{os.cpu_count()} logical CPUs, {len(os.sched_getaffinity(0))} usable, {args.threads} threads; "
        f"load average at start {os.getloadavg()[0]:.2f}"
    )
    rows, steps, gpu_memory = [], {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        formats = export_formats(backends)
        if formats:  # the eager backends need no export
            export_model(model, tmp, formats)
        for backend in backends:
            network = build_network(backend, model, Path(tmp), args.device, args.threads)
            if network is None:
                print(f"{backend}: not installed; no row")
                continue
            if args.device == "cuda":
                torch.cuda.reset_peak_memory_stats()
            for scan_name in args.scans.split(","):
                scans = stream_scans(scan_name)
                if scans is None:
                    print(f"{scan_name}: no scans under {DATA}; no rows")
                    continue
                contract = InputContract(Preprocessing.from_teacher(TEACHERS[scan_name]), True, model.grid)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # the height-frame lift of velodyne scans, said once per stream
                    times, memory, spent = play(network, contract, backend, scans, regimes, args.passes)
                for regime, values in times.items():
                    rows.append((scan_name, len(scans[0]), regime, backend, values, memory.get(regime)))
                if spent:
                    steps[(scan_name, backend)] = spent
            if args.device == "cuda":
                gpu_memory[backend] = torch.cuda.max_memory_allocated() / 2**20
    print(f"| stream | points | regime | engine | median ms | p90 ms | Hz | vs {regimes[0]} | memory MB |")
    print("|---|---|---|---|---|---|---|---|---|")
    base = {}
    for scan_name, points, regime, backend, values, memory in rows:
        median, p90 = statistics.median(values), float(np.percentile(values, 90))
        base.setdefault((scan_name, backend), median)
        shown = "" if memory is None else f"{memory:.0f}"
        print(
            f"| {scan_name} | {points} | {regime} | {backend} | {1000 * median:.1f} | {1000 * p90:.1f} | "
            f"{1 / median:.1f} | {base[(scan_name, backend)] / median:.2f}x | {shown} |"
        )
    for (scan_name, backend), spent in steps.items():
        parts = ", ".join(f"{key} {1000 * value:.1f} ms" for key, value in spent.items())
        print(f"{scan_name}, {backend}, streamed: median per frame: {parts}")
    if gpu_memory:
        print("GPU memory, peak allocated by torch: " + ", ".join(f"{k} {v:.0f} MB" for k, v in gpu_memory.items()))
    print(
        f"median and p90 of the frames after the first two of each of {args.passes} passes "
        f"({len(rows[0][4]) if rows else 0} frames per row); load average at the end "
        f"{os.getloadavg()[0]:.2f}"
    )


def play(network, contract, backend, scans, regimes, passes):
    """Per-frame seconds of each of ``regimes`` (pairwise, streamed, given), the streamed regime's RSS growth and
    its median time per step (empty when it is not played)."""
    times = {regime: [] for regime in regimes}
    predictor = Predictor(network, contract, backend)
    # the given regime's inputs: the stream's own estimates, computed once beforehand
    if "given" in times:
        reference = FlowStream(Predictor(network, contract, backend))
        given = [reference.push(scan).prediction for scan in scans]
        lift = predictor.frame_lift(scans[0])
        grounds = [predictor.ground_mask("g", lift_points(scan, lift), None) for scan in scans]
    memory, per_step = {}, []
    for _ in range(passes):
        for k in range(1, len(scans)):
            if "pairwise" in times:
                start = time.perf_counter()
                predictor.predict(scans[k - 1], scans[k])
                if k > 2:
                    times["pairwise"].append(time.perf_counter() - start)
            if "given" in times:
                start = time.perf_counter()
                predictor.predict(scans[k - 1], scans[k], given[k].ego1_from_ego0, grounds[k - 1], grounds[k])
                if k > 2:
                    times["given"].append(time.perf_counter() - start)
        if "streamed" not in times:
            continue
        before = rss_mb()
        stream = FlowStream(Predictor(network, contract, backend))
        clock = StepClock(stream)
        for k, scan in enumerate(scans):
            clock.take()
            start = time.perf_counter()
            stream.push(scan)
            seconds = time.perf_counter() - start
            spent = clock.take()
            if k > 2:
                times["streamed"].append(seconds)
                per_step.append({**spent, "the rest": seconds - sum(spent.values())})
        memory["streamed"] = max(memory.get("streamed", 0.0), rss_mb() - before)
    medians = {key: statistics.median(step[key] for step in per_step) for key in per_step[0]} if per_step else {}
    return times, memory, medians


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="mode", required=True)
    lat = sub.add_parser("latency")  # the one mode (the ego-motion error: benchmarks/bench_ego_motion.py)
    lat.add_argument("--model", default="fastflow3d_small")
    lat.add_argument("--threads", type=int, default=2)
    lat.add_argument("--backends", default="onnx-tuned,openvino")
    lat.add_argument("--scans", default="kitti,av2")
    lat.add_argument("--passes", type=int, default=5)
    lat.add_argument("--regimes", default="pairwise,streamed,given")
    lat.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="where the network runs")
    args = parser.parse_args()
    latency(args)


if __name__ == "__main__":
    main()
