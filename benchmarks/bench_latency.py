"""FastFlow3D inference latency per frame pair: eager PyTorch, torch.compile, torch.export (.pt2) and ONNX
Runtime.

Usage: python benchmarks/bench_latency.py [--device cpu|cuda] [--points 80000] [--runs 20] [--warmup 3]
    [--model fastflow3d|fastflow3d_small|fastflow3d_xl] [--cell 0.2] [--threads N] [--backends eager,compile,pt2,onnx]

Times the exported single-sample network (voxelisation + UNet + per-point head; numpy in, numpy out, so host <->
device copies are included on a GPU) on two uniform random scans of ``--points`` points each over the default
102.4 m x 102.4 m x 6 m range (AV2 size after ground removal: about 80k points), grid 512 x 512 at 0.2 m. The
model has random weights (latency does not depend on them). Exports are made on the CPU and checked against eager
by ``fastflow3d.export``; the ``torch.export`` program then runs on ``--device``, ONNX Runtime with the CUDA execution
provider on ``cuda`` (the row is left out, with a note, when onnxruntime has no CUDA provider) and the CPU one on
``cpu``; torch.compile (``dynamic=True``, default mode) is checked against eager before it is timed. Default
backends: all four on ``cuda``; on ``cpu`` all but torch.compile, whose first call takes minutes there (about 2 min
on 2 cores for a 128 x 128 grid; name it in ``--backends`` to time it anyway). On ``cuda`` cuDNN autotuning is on
(the pseudo-image has a fixed size). Prints the median and minimum of ``--runs`` calls after ``--warmup`` calls
(the backends take turns within each run, so that a change of load hits all alike) and each backend's speed
relative to eager; one more row times the whole ``Predictor`` call (ego compensation and ego flow added back,
transform given) with ONNX Runtime.
"""

import argparse
import copy
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from fastflow3d.artifact import FILE_NAMES, OnnxRuntimeNetwork, SingleSampleNet, TorchNetwork, load_network
from fastflow3d.checkpoint import build_student
from fastflow3d.export import PARITY_TOLERANCE, export_model
from fastflow3d.model import FastFlow3D
from fastflow3d.predictor import Predictor
from icpflow.geometry import make_transform

#: the paper's FastFlow3D settings (the one place of the model's settings); --cell changes the pillar size
CONF = Path(__file__).resolve().parents[1] / "conf"


def model_config(name: str) -> dict:
    """``conf/model/<name>.yaml`` as train.py composes it (the small and XL models extend the paper's)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return OmegaConf.to_container(compose("train", [f"model={name}"]).model, resolve=True)


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


def device_name(device: str) -> str:
    return torch.cuda.get_device_name() if device == "cuda" else cpu_name()


def onnx_providers(device: str) -> list[str] | None:
    """ONNX Runtime providers for ``device``; None when it has no CUDA provider for ``cuda``."""
    import onnxruntime

    if device == "cpu":
        return ["CPUExecutionProvider"]
    if "CUDAExecutionProvider" not in onnxruntime.get_available_providers():
        return None
    return ["CUDAExecutionProvider", "CPUExecutionProvider"]


def compiled_network(model: FastFlow3D, device: str, pc0: np.ndarray, pc1: np.ndarray) -> TorchNetwork:
    """``torch.compile`` of the single-sample network on ``device``, compiled by its first call on (pc0, pc1) and
    checked against eager there."""
    eager = SingleSampleNet(copy.deepcopy(model).to(device)).eval()
    network = TorchNetwork(torch.compile(eager, dynamic=True), device)
    start = time.perf_counter()
    residual, valid = network(pc0, pc1)
    expected, expected_valid = TorchNetwork(eager, device)(pc0, pc1)
    error = float(np.abs(residual - expected).max(initial=0.0))
    if not error <= PARITY_TOLERANCE or not np.array_equal(valid, expected_valid):
        sys.exit(f"bench_latency: torch.compile differs from eager by {error:.3g} m or in its validity mask")
    print(
        f"torch.compile: first call (compilation) {time.perf_counter() - start:.1f} s; max |compiled - eager| "
        f"{error:.1e} m"
    )
    return network


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--points", type=int, default=80_000)
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--model", default="fastflow3d", help="a conf/model option (fastflow3d_small: CPU recipes)")
    parser.add_argument("--cell", type=float, default=None, help="pillar size in m (default: the model's)")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument(
        "--backends",
        default=None,
        help="comma-separated subset of eager,compile,pt2,onnx (default: all on cuda, all but compile on cpu)",
    )
    args = parser.parse_args()
    device = args.device
    if device == "cuda" and not torch.cuda.is_available():
        sys.exit("bench_latency: --device cuda but torch sees no CUDA device (a CPU build of torch?)")
    torch.set_num_threads(args.threads)
    torch.backends.cudnn.benchmark = device == "cuda"
    default = "eager,compile,pt2,onnx" if device == "cuda" else "eager,pt2,onnx"
    backends = [name.strip() for name in (args.backends or default).split(",") if name.strip()]
    unknown = sorted(set(backends) - {"eager", "compile", "pt2", "onnx"})
    if unknown:
        sys.exit(f"bench_latency: unknown backend(s) {', '.join(unknown)}; use eager, compile, pt2, onnx")
    config = model_config(args.model)
    model = build_student({**config, "cell": args.cell or config["cell"]}).eval()
    pc0, pc1 = random_scan(args.points, 0), random_scan(args.points, 1)
    ego = make_transform(yaw=0.01, translation=(1.0, 0.05, 0.0))
    load = os.getloadavg()
    print(
        f"FastFlow3D grid {model.grid.nx}x{model.grid.ny}, {args.points} points per scan, {device}: "
        f"{device_name(device)}, {os.cpu_count()} logical CPUs, torch {args.threads} threads, torch "
        f"{torch.__version__}, load average at start {load[0]:.2f}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        formats = [name for name in ("onnx", "pt2") if name in backends]
        start = time.perf_counter()
        metadata = export_model(model, tmp, formats) if formats else {"parity_max_abs_m": {}}
        if formats:
            print(
                f"export + parity check: {time.perf_counter() - start:.1f} s; max |export - eager| "
                + ", ".join(f"{k} {v:.1e} m" for k, v in metadata["parity_max_abs_m"].items())
            )
        networks = {}
        if "eager" in backends:
            networks["eager"] = TorchNetwork(SingleSampleNet(copy.deepcopy(model).to(device)).eval(), device)
        if "compile" in backends:
            networks["torch.compile"] = compiled_network(model, device, pc0, pc1)
        if "pt2" in backends:
            networks["pt2"] = load_network(Path(tmp) / FILE_NAMES["pt2"], "pt2", device)
        if "onnx" in backends:
            providers = onnx_providers(device)
            if providers is None:
                print("onnxruntime has no CUDAExecutionProvider here (pip install onnxruntime-gpu): no ONNX row")
            else:
                import onnxruntime

                networks["onnx"] = OnnxRuntimeNetwork(Path(tmp) / "fastflow3d.onnx", providers)
                print(f"onnxruntime {onnxruntime.__version__}, providers {networks['onnx'].session.get_providers()}")
        calls = {
            f"{name} (network: voxelisation + UNet + head)": (lambda network=network: network(pc0, pc1))
            for name, network in networks.items()
        }
        if "onnx" in networks:
            predictor = Predictor(networks["onnx"], {"preprocessing": {"remove_ground": False}}, "onnx")
            calls["onnx Predictor call (+ ego compensation, ego flow)"] = lambda: predictor(pc0, pc1, ego)
        rows = list(timed(calls, args.runs, args.warmup).items())
    base = statistics.median(rows[0][1]) if "eager" in networks else None  # eager is the first row when timed
    print(f"| backend ({device}) | median ms | min ms | runs | speed vs eager |")
    print("|---|---|---|---|---|")
    for name, times in rows:
        median = statistics.median(times)
        ratio = f"{base / median:.2f}x" if base else "-"
        print(f"| {name} | {1000 * median:.1f} | {1000 * min(times):.1f} | {len(times)} | {ratio} |")
    print(f"load average at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
