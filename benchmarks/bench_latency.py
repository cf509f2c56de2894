"""FastFlow3D inference latency per frame pair: eager PyTorch, TorchScript and ONNX Runtime on this CPU.

Usage: python benchmarks/bench_latency.py [--points 80000] [--runs 20] [--warmup 3] [--cell 0.2] [--threads N]
    [--backends eager,torchscript,onnx]

Times the exported single-sample network (voxelisation + UNet + per-point head; numpy in, numpy out) on two
uniform random scans of ``--points`` points each over the default 102.4 m x 102.4 m x 6 m range (AV2 size after
ground removal: about 80k points), grid 512 x 512 at 0.2 m. The model has random weights (latency does not depend
on them); each export is checked against eager by ``fastflow3d.export`` before it is timed. Prints the median and
minimum of ``--runs`` calls after ``--warmup`` calls (the backends take turns within each run, so that a change of
load hits all alike) and each backend's speed relative to eager; one more row times the whole ``Predictor`` call
(ego compensation and ego flow added back, transform given) with ONNX Runtime.
"""

import argparse
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from fastflow3d.export import SingleSampleNet, export_model
from fastflow3d.model import FastFlow3D
from fastflow3d.predictor import Predictor, TorchNetwork, load_network
from icpflow.geometry import make_transform


def random_scan(points: int, seed: int) -> np.ndarray:
    """(points, 3) float32 uniform over [-51.2, 51.2]^2 x [-3, 3]."""
    rng = np.random.default_rng(seed)
    return (rng.random((points, 3)) * [102.4, 102.4, 6.0] - [51.2, 51.2, 3.0]).astype(np.float32)


def timed(calls: dict, runs: int, warmup: int) -> dict[str, list[float]]:
    """Wall-clock seconds of ``runs`` calls of each function after ``warmup`` calls; the functions take turns
    within each run, so that a change of load on a shared machine hits all of them alike."""
    for fn in calls.values():
        for _ in range(warmup):
            fn()
    times = {name: [] for name in calls}
    for _ in range(runs):
        for name, fn in calls.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    return times


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=80_000)
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--cell", type=float, default=0.2)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--backends", default="eager,torchscript,onnx")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    backends = [name.strip() for name in args.backends.split(",") if name.strip()]
    model = FastFlow3D(cell=args.cell).eval()
    pc0, pc1 = random_scan(args.points, 0), random_scan(args.points, 1)
    ego = make_transform(yaw=0.01, translation=(1.0, 0.05, 0.0))
    load = os.getloadavg()
    print(f"FastFlow3D grid {model.grid.nx}x{model.grid.ny}, {args.points} points per scan, {cpu_name()}, "
          f"{os.cpu_count()} logical CPUs, torch {args.threads} threads, torch {torch.__version__}, "
          f"load average at start {load[0]:.2f}")
    with tempfile.TemporaryDirectory() as tmp:
        formats = [name for name in ("onnx", "torchscript") if name in backends]
        start = time.perf_counter()
        metadata = export_model(model, tmp, formats) if formats else {"parity_max_abs_m": {}}
        if formats:
            print(f"export + parity check: {time.perf_counter() - start:.1f} s; max |export - eager| "
                  + ", ".join(f"{k} {v:.1e} m" for k, v in metadata["parity_max_abs_m"].items()))
        networks = {}
        if "eager" in backends:
            networks["eager"] = TorchNetwork(SingleSampleNet(model).eval())
        if "torchscript" in backends:
            networks["torchscript"] = load_network(Path(tmp) / "fastflow3d.pt", "torchscript", "cpu")
        if "onnx" in backends:
            networks["onnx"] = load_network(Path(tmp) / "fastflow3d.onnx", "onnx", "cpu")
            import onnxruntime

            print(f"onnxruntime {onnxruntime.__version__}, providers {networks['onnx'].session.get_providers()}")
        calls = {f"{name} (network: voxelisation + UNet + head)": (lambda network=network: network(pc0, pc1))
                 for name, network in networks.items()}
        if "onnx" in networks:
            predictor = Predictor(networks["onnx"], {}, "onnx")
            calls["onnx Predictor call (+ ego compensation, ego flow)"] = lambda: predictor(pc0, pc1, ego)
        rows = list(timed(calls, args.runs, args.warmup).items())
    base = statistics.median(rows[0][1]) if "eager" in networks else None  # eager is the first row when timed
    print("| backend | median ms | min ms | runs | speed vs eager |")
    print("|---|---|---|---|---|")
    for name, times in rows:
        median = statistics.median(times)
        ratio = f"{base / median:.2f}x" if base else "-"
        print(f"| {name} | {1000 * median:.0f} | {1000 * min(times):.0f} | {len(times)} | {ratio} |")
    print(f"load average at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
