"""FastFlow3D inference latency per frame pair: the whole ``Predictor`` call on real scans, per backend and regime.

    .venv/bin/python benchmarks/bench_latency.py [--model fastflow3d_small] [--decoder linear|gru] [--threads 2]
        [--runs 20] [--warmup 3] [--scans kitti,av2] [--regimes given,estimated]
        [--backends eager,eager-bf16,pt2,onnx,onnx-tuned,openvino,openvino-bf16] [--breakdown] [--device cpu|cuda]

The model (``conf/model/<model>.yaml``, ``--decoder`` and ``--set key=value`` overriding its fields) has random
weights (latency does not depend on them) and is exported (ONNX + torch.export) and checked against eager by
``fastflow3d.artifact.export``; every backend is then checked again against eager on the export's check clouds
(``parity``, metres) and on each real scan (``real``). Backends: ``eager`` PyTorch (``eager-bf16``: under bfloat16
autocast), ``compile`` (torch.compile, dynamic; its first call takes minutes on a CPU), ``pt2`` (torch.export), ``onnx``
(ONNX Runtime with its default session, the Predictor's before this benchmark's issue; with ``--device cuda`` its CUDA
provider), ``onnx-tuned`` and ``openvino`` / ``openvino-bf16`` (``fastflow3d.artifact.engines``; OpenVINO rows need
``pip install 'icpflow[openvino]'`` and are left out without it).

Scans: KITTI HDL-64E ``000000`` -> ``000001`` (``../shared/data/kitti_hdl64_scans``, ~124k points each) and the
Argoverse 2 pair (``../shared/data/av2``, ~99k points each); ``uniform`` adds ``--points`` uniform random points over
the grid (the given regime only, with the identity). Regimes: ``given`` (ego motion and both ground masks passed
in, as from a dataset's poses and labels; they are computed once beforehand, outside the timing) and ``estimated``
(none passed: the Predictor finds both scans' ground, ``icpflow.ground``, and the ego motion, ``icpflow.odometry``).
The model removes ground (``preprocessing.remove_ground``, as the CPU recipes train it) with the teacher settings of
the scan's dataset.

Prints, per scan, regime and backend: median and p90 of ``--runs`` calls after ``--warmup`` calls (the backends
take turns within each run, so that a change of load on a shared machine hits all alike), frames per second
(1 / median), speed relative to the first backend, and memory: the process's resident-set growth when the backend
was built and warmed up (MB). ``--breakdown`` adds what one call's time is made of (first backend, per step).
"""

from __future__ import annotations

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

from fastflow3d.artifact.checkpoint import build_student
from fastflow3d.artifact.engines import BF16_TOLERANCE, TorchNetwork, load_network
from fastflow3d.artifact.export import PARITY_TOLERANCE, export_model, measure_parity
from fastflow3d.artifact.file_format import FILE_NAMES, SingleSampleNet
from fastflow3d.inference.predictor import Predictor
from fastflow3d.network.contract import InputContract
from fastflow3d.network.model import compensate
from fastflow3d.training import options as fastflow3d_options
from icpflow.geometry import residual_to_full
from icpflow.preprocess import Preprocessing
from icpflow.teacher.config import ICPFlowConfig

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
DATA = ROOT.parent / "shared" / "data"
BACKENDS = ("eager", "eager-bf16", "compile", "pt2", "onnx", "onnx-tuned", "openvino", "openvino-bf16")
#: teacher settings of each scan's dataset (ground segmentation and ego motion in the ``estimated`` regime)
TEACHERS = {
    "kitti": ICPFlowConfig.preset("waymo", ground={"method": "patchwork", "patchwork_z_offset": 0.0}, crop_xy=51.2),
    "av2": ICPFlowConfig.preset("av2"),
    "uniform": ICPFlowConfig.preset("av2"),
}


def model_config(name: str, overrides: list[str]) -> dict:
    """``conf/model/<name>.yaml`` as train.py composes it, with ``model.<key>=<value>`` overrides."""
    from hydra import compose, initialize_config_dir

    fastflow3d_options.register()  # the schemas the configs extend, as the entry script stores them
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("train", [f"model={name}", *(f"model.{item}" for item in overrides)])
        return OmegaConf.to_container(cfg.model, resolve=True)


def read_scans(name: str, points: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(pc0, pc1) float32 of a shipped scan pair, or None where ../shared/data lacks it."""
    if name == "kitti":
        files = sorted((DATA / "kitti_hdl64_scans").glob("*.bin"))[:2]
        if len(files) < 2:
            return None
        return tuple(np.fromfile(f, dtype=np.float32).reshape(-1, 4)[:, :3].copy() for f in files)
    if name == "av2":
        import pandas as pd

        sweeps = sorted((DATA / "av2" / "sensor" / "val").glob("*/sensors/lidar/*.feather"))[:2]
        if len(sweeps) < 2:
            return None
        return tuple(pd.read_feather(s, columns=["x", "y", "z"]).to_numpy().astype(np.float32) for s in sweeps)
    rng = np.random.default_rng(0)
    return tuple((rng.random((points, 3)) * [64.0, 64.0, 4.0] - [32.0, 32.0, 1.0]).astype(np.float32) for _ in "01")


def rss_mb() -> float:
    """Current resident set size of this process (MB)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def export_formats(backends) -> list[str]:
    """The export files ``backends`` run from: ``onnx`` (ONNX Runtime and OpenVINO), ``pt2``; none for eager."""
    return [f for f in ("onnx", "pt2") if any(b.startswith(f) or (f == "onnx" and "openvino" in b) for b in backends)]


def build_network(name: str, model, export_dir: Path, device: str, threads: int):
    """The runnable network of backend ``name`` (numpy in, numpy out); None when its runtime is not installed. The
    exported files open through ``fastflow3d.artifact.engines.load_network``, as the Predictor opens them."""
    onnx_file = export_dir / FILE_NAMES["onnx"]
    if name in ("eager", "eager-bf16"):
        return TorchNetwork(SingleSampleNet(copy.deepcopy(model).to(device)).eval(), device, name == "eager-bf16")
    if name == "compile":
        return TorchNetwork(
            torch.compile(SingleSampleNet(copy.deepcopy(model).to(device)).eval(), dynamic=True), device
        )
    if name == "pt2":
        return load_network(export_dir / FILE_NAMES["pt2"], "pt2", device)
    if name == "onnx":
        providers = ["CUDAExecutionProvider", "CPUExecutionProvider"] if device == "cuda" else ["CPUExecutionProvider"]
        return load_network(onnx_file, "onnx", providers=providers)
    if name.startswith("openvino"):
        try:
            import openvino  # noqa: F401
        except ImportError:
            return None
        precision = "bf16" if name.endswith("bf16") else "f32"
        return load_network(onnx_file, "onnx", runtime="openvino", threads=threads, precision=precision)
    return load_network(onnx_file, "onnx", runtime="onnxruntime", threads=threads)


def timed(calls: dict, runs: int, warmup: int) -> dict[str, list[float]]:
    """Wall-clock seconds of ``runs`` calls of each function after ``warmup`` calls, taking turns within a run."""
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


def breakdown(predictor: Predictor, pc0, pc1, runs: int) -> dict[str, float]:
    """Median seconds of each step of one ``estimated``-regime Predictor call (the steps of ``Predictor.predict``)."""
    steps = {k: [] for k in ("ground (2 scans)", "ego motion (odometry, a pair)", "network", "the rest")}
    for _ in range(runs):
        t0 = time.perf_counter()
        g0, g1 = predictor.ground_mask("ground0", pc0, None), predictor.ground_mask("ground1", pc1, None)
        t1 = time.perf_counter()
        ego = predictor.estimate_ego_motion(pc0, pc1, g0, g1)
        t2 = time.perf_counter()
        moved = compensate(pc0[~g0], ego)
        t3 = time.perf_counter()
        kept, valid = predictor.network(moved, pc1[~g1])
        t4 = time.perf_counter()
        residual = np.zeros((len(pc0), 3), np.float32)
        residual[~g0] = np.where(valid[:, None], kept, 0.0)
        residual_to_full(residual, pc0, ego)
        t5 = time.perf_counter()
        for key, value in zip(steps, (t1 - t0, t2 - t1, t4 - t3, (t3 - t2) + (t5 - t4))):
            steps[key].append(value)
    return {key: statistics.median(values) for key, values in steps.items()}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--model", default="fastflow3d_small", help="a conf/model option (fastflow3d_small: CPU recipes)"
    )
    parser.add_argument("--decoder", default=None, help="the model's decoder (a model.decoder override)")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="more model.<key> overrides")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--threads", type=int, default=2, help="torch, ONNX Runtime and OpenVINO threads")
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--scans", default="kitti,av2", help="comma-separated: kitti, av2, uniform")
    parser.add_argument("--points", type=int, default=80_000, help="points per scan of the uniform scans")
    parser.add_argument("--regimes", default="given,estimated", help="comma-separated: given, estimated")
    parser.add_argument("--backends", default="onnx,onnx-tuned,openvino,eager")
    parser.add_argument("--breakdown", action="store_true", help="also time each step of the first backend's call")
    args = parser.parse_args()
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    unknown = sorted(set(backends) - set(BACKENDS))
    if unknown or not backends:
        sys.exit(f"bench_latency: --backends: unknown {', '.join(unknown) or '(none)'}; use {', '.join(BACKENDS)}")
    if args.device == "cuda" and not torch.cuda.is_available():
        sys.exit("bench_latency: --device cuda but torch sees no CUDA device (a CPU build of torch?)")
    torch.set_num_threads(args.threads)
    overrides = ([f"decoder={args.decoder}"] if args.decoder else []) + list(args.set)
    model = build_student(model_config(args.model, overrides)).eval()
    print(
        f"model {args.model} {' '.join(overrides)} grid {model.grid.nx}x{model.grid.ny}; {args.device}: {cpu_name()}, "
        f"{os.cpu_count()} logical CPUs, {args.threads} threads, torch {torch.__version__}, load average at start "
        f"{os.getloadavg()[0]:.2f}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        formats = export_formats(backends)
        if formats:
            export_model(model, tmp, formats)
        eager_net = SingleSampleNet(copy.deepcopy(model)).eval()
        networks, memory, parity = {}, {}, {}
        for name in backends:
            before = rss_mb()
            network = build_network(name, model, Path(tmp), args.device, args.threads)
            if network is None:
                print(f"{name}: not installed (pip install 'icpflow[openvino]'); no row")
                continue
            parity[name] = measure_parity(eager_net, network) if args.device == "cpu" else float("nan")
            tolerance = BF16_TOLERANCE if name.endswith("bf16") else PARITY_TOLERANCE
            if args.device == "cpu" and not parity[name] <= tolerance:  # on CUDA: not measured (nan)
                print(f"{name}: differs from eager by {parity[name]:.3g} m (> {tolerance:g} m); no row")
                continue
            networks[name], memory[name] = network, rss_mb() - before
        print(
            "parity, max |backend - eager| on the export's check clouds (m): "
            + ", ".join(f"{k} {v:.1e}" for k, v in parity.items())
        )
        rows = []
        for scan in [s.strip() for s in args.scans.split(",") if s.strip()]:
            data = read_scans(scan, args.points)
            if data is None:
                print(f"{scan}: no scans under {DATA}; no rows")
                continue
            pc0, pc1 = data
            contract = InputContract(Preprocessing.from_teacher(TEACHERS[scan]), True, model.grid)
            predictors = {name: Predictor(net, contract, name) for name, net in networks.items()}
            first = next(iter(predictors.values()))
            g0, g1 = first.ground_mask("ground0", pc0, None), first.ground_mask("ground1", pc1, None)
            # the given regime's inputs, outside the timing (uniform points have no surfaces to register: the identity)
            ego = np.eye(4) if scan == "uniform" else first.estimate_ego_motion(pc0, pc1, g0, g1)
            reference = predictors.get("eager") or first
            expected = reference(pc0, pc1, ego, g0, g1)
            real = {name: float(np.abs(p(pc0, pc1, ego, g0, g1) - expected).max()) for name, p in predictors.items()}
            kept = int((~g0).sum())
            for regime in [r.strip() for r in args.regimes.split(",") if r.strip()]:
                if regime == "estimated" and scan == "uniform":
                    print("uniform: no estimated regime (random points give the odometry nothing to register)")
                    continue
                given = (ego, g0, g1) if regime == "given" else (None, None, None)
                calls = {name: (lambda p=p, a=pc0, b=pc1, g=given: p(a, b, *g)) for name, p in predictors.items()}
                for name, times in timed(calls, args.runs, args.warmup).items():
                    rows.append((scan, f"{len(pc0)} ({kept} non-ground)", regime, name, times, real[name]))
            if args.breakdown:
                steps = breakdown(first, pc0, pc1, max(3, args.runs // 2))
                print(
                    f"{scan}, {next(iter(predictors))}: one estimated-regime call, median s per step: "
                    + ", ".join(f"{k} {1000 * v:.1f} ms" for k, v in steps.items())
                )
    head = f"| scan | points pc0 | regime | backend | median ms | p90 ms | Hz | vs {backends[0]} | memory MB |"
    print(head + " real-scan max |d| m |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    base = {}
    for scan, points, regime, name, times, error in rows:
        median, p90 = statistics.median(times), float(np.percentile(times, 90))
        base.setdefault((scan, regime), median)
        print(
            f"| {scan} | {points} | {regime} | {name} | {1000 * median:.1f} | {1000 * p90:.1f} | {1 / median:.1f} | "
            f"{base[(scan, regime)] / median:.2f}x | {memory[name]:.0f} | {error:.1e} |"
        )
    print(f"median and p90 of {args.runs} calls after {args.warmup}; load average at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
