"""FastFlow3D inference latency on real scans, in three modes: a frame pair (``pair``), a stream (``stream``) and
the refinement dial (``refine``).

    .venv/bin/python -m benchmarks.bench_student_latency [--mode pair] [--model fastflow3d_small]
        [--decoder linear|gru] [--set KEY=VALUE ...] [--threads 2] [--runs 20] [--warmup 3] [--scans kitti,av2]
        [--regimes given,estimated] [--backends eager,eager-bf16,pt2,onnx,onnx-tuned,onnx-int8,openvino,openvino-bf16]
        [--breakdown] [--device cpu|cuda]
    .venv/bin/python -m benchmarks.bench_student_latency --mode stream [--backends onnx-tuned,onnx-int8,openvino]
        [--scans kitti,av2] [--passes 5] [--threads 2] [--model fastflow3d_small] [--regimes pairwise,streamed,given]
        [--device cpu|cuda]
    .venv/bin/python -m benchmarks.bench_student_latency --mode refine --export <export dir> [--runs 20]
        [--warmup 3] [--scans kitti,av2]
    .venv/bin/python -m benchmarks.bench_student_latency --mode cli --export <export dir> [--passes 3] [--threads 2]
        [--scans kitti,av2,synthetic] [--backends default,onnxruntime,onnxruntime-int8,openvino,openvino-bf16,pt2]
        [--device cpu|cuda]

Scans: KITTI HDL-64E ``000000`` -> ``000001`` (``../shared/data/kitti_hdl64_scans``, ~124k points each) and the
Argoverse 2 pair (``../shared/data/av2``, ~99k points each); ``uniform`` (pair mode) adds ``--points`` uniform
random points over the grid (the given regime only, with the identity). In the pair and stream modes the model
(``conf/model/<model>.yaml``, ``--decoder`` and ``--set key=value`` overriding its fields) has random weights
(latency does not depend on them) and removes ground (``preprocessing.remove_ground``, as the CPU recipes train
it) with the teacher settings of the scan's dataset. Backends: ``eager`` PyTorch (``eager-bf16``: under bfloat16
autocast), ``compile`` (torch.compile, dynamic; its first call takes minutes on a CPU), ``pt2`` (torch.export),
``onnx`` (ONNX Runtime with its default session, the Predictor's before issue 22; with ``--device cuda`` its CUDA
provider where ``onnxruntime-gpu`` is installed, else its CPU provider), ``onnx-tuned`` and ``openvino`` /
``openvino-bf16`` (``fastflow3d.artifact.engines``, the CPU engines; OpenVINO rows need ``pip install
'icpflow[openvino]'`` and are left out without it), ``onnx-int8`` (the tuned ONNX Runtime session on the int8
network, ``fastflow3d.artifact.quantize``, its ranges from 4 synthetic pairs; its parity is printed, not gated: its
accuracy is checked at export, on a trained network and labelled pairs).

``pair``: the whole ``Predictor`` call per frame pair, per backend and regime. The model is exported (ONNX +
torch.export) and checked against eager by ``fastflow3d.artifact.export``; every backend is then checked again against
eager on the export's check clouds (``parity``, metres) and on each real scan (``real``). Regimes: ``given`` (ego motion
and both ground masks passed in, as from a dataset's poses and labels; they are computed once beforehand, outside
the timing) and ``estimated`` (none passed: the Predictor finds both scans' ground, ``icpflow.scans.ground``, and the
ego motion, ``icpflow.scans.odometry``). Prints, per scan, regime and backend: median and p90 of ``--runs`` calls after
``--warmup`` calls (the backends take turns within each run, so that a change of load on a shared machine hits all
alike), frames per second (1 / median), speed relative to the first backend, and memory: the process's
resident-set growth when the backend was built and warmed up (MB). ``--breakdown`` adds what one call's time is
made of (first backend, per step).

``stream``: streaming inference (``fastflow3d.inference.stream.FlowStream``), per-frame latency. Each scan list is
played as a stream (KITTI HDL-64E ``000000``-``000005``; the two AV2 sweeps alternate, s0 s1 s0 s1 ..., as the only AV2
stream shipped) ``--passes`` times from a fresh stream; the frames after the first two of each pass are timed (the whole
``push``). Regimes: ``pairwise`` (``Predictor.predict`` on each pair with nothing given), ``streamed`` (nothing
given), ``overlapped`` (the same with ``FlowStream(overlap=True)``: each pair's network in a worker thread beside the
next scan's ground and odometry; a push returns the step before, so a push is a frame) and ``given`` (the ego motion and
ground masks passed in, computed beforehand). With ``--device cuda`` only the network runs on the GPU: ground, odometry
and the rest stay on the CPU's ``--threads``. Prints median / p90 ms, Hz, the RSS growth of the stream (and the GPU's
peak memory), and the streamed regime's time per step (ground, odometry, network, the rest). The ego motion's error
against true poses, streamed and pairwise: ``benchmarks/bench_ego_motion.py``.

``refine``: the refinement dial, whole-call time of a trained student (``--export``) alone, with the Predictor's
ICP refinement (``fastflow3d.inference.refine``) and of the teacher. Ego motion and ground masks are given (computed
once beforehand with the student's preprocessing: KISS-ICP and Patchwork++), as in the pair mode's ``given`` regime;
the teacher gets the same ego motion and masks. The student runs in float32 as ``Predictor.load`` picks its engine
(ONNX Runtime, tuned, on the CPU; precision f32 by name, as BENCHMARKS.md's figures: the default, auto, would run an
export's int8 network); the three calls take turns within each run. These scans have no ground-truth flow: the
accuracy side of the dial is ``eval.py ... method=[ego,icpflow,student,student+refine]`` on the synthetic test split
(BENCHMARKS.md). Prints median and p90 ms, Hz, and for the refinement the share of the network's points whose flow
ICP replaced and their median change (m).

``cli``: the stream as a user runs it, ``fastflow3d-infer EXPORT DIR --out OUT [--refine]`` in a process of its own,
whole runs (reading, every step and writing), on KITTI (the six HDL-64E scans forth and back, 26 scans), AV2 (the two
sweeps alternating, 26 scans; ``--frames`` sets both lengths, the GPU run's smoke test 8) and a synthetic test sequence
(40 frames), with and without the refinement, per
``--backends`` (``default``: the command as a user types it, neither ``--runtime`` nor ``--precision``, the table naming
the precision ``auto`` chose from the run's manifest; else the CLI's ``--runtime``, given only where it is not ONNX
Runtime, the CLI's default engine, and ``--precision`` after a dash, ``f32`` where none: ``onnxruntime-int8`` runs the
export's int8 network, which ``export.py ... int8=true`` writes; ``pt2``: the export's torch.export program on
``--device``, the network on a GPU with ``--device cuda``). Prints median and p90 ms per frame and Hz, the host
(``benchmarks.common.cpu_name``) and the first engine's network alone on one thread, the figure that compares hosts
(:func:`network_alone`). The accuracy of the same stream: ``eval.py ... method=[student-stream,student-stream+refine]
[precision=f32|int8]`` (its default, ``auto``, as the CLI). A frame's time is the time between
consecutive flow files (the first two left out, and the last ``STREAM_DEPTH``, written after the last scan was read:
until issue 44's ninth session they were timed, and with the six KITTI scans one of a run's two timed intervals was such
a flush, the last pair's network alone, 50-60 ms against a frame's 70-90).
"""

from __future__ import annotations

import argparse
import copy
import itertools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from benchmarks.common import DATA, compose, cpu_name, open_split, read_scan_pair, rss_mb, timed
from fastflow3d.artifact.checkpoint import build_student
from fastflow3d.artifact.engines import BF16_TOLERANCE, TorchNetwork, load_network
from fastflow3d.artifact.export import PARITY_TOLERANCE, export_model, measure_parity
from fastflow3d.artifact.file_format import FILE_NAMES, INT8_FILE_NAME, SingleSampleNet
from fastflow3d.artifact.quantize import write_int8
from fastflow3d.inference.cli import STREAM_DEPTH
from fastflow3d.inference.predictor import Predictor
from fastflow3d.inference.scan_files import read_raw_scan
from fastflow3d.inference.stream import FlowStream
from fastflow3d.inference.stream_folder import MANIFEST
from fastflow3d.network.contract import InputContract
from fastflow3d.network.model import compensate
from icpflow.core.geometry import residual_to_full
from icpflow.core.threads import available_cores
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.scans.preprocess import Preprocessing, lift_points, lift_transform
from icpflow.teacher import ICPFlow
from icpflow.teacher.config import ICPFlowConfig

BACKENDS = ("eager", "eager-bf16", "compile", "pt2", "onnx", "onnx-tuned", "onnx-int8", "openvino", "openvino-bf16")
#: teacher settings of each scan's dataset (ground segmentation and ego motion in the ``estimated`` regime)
TEACHERS = {
    "kitti": ICPFlowConfig.preset("waymo", ground={"method": "patchwork", "patchwork_z_offset": 0.0}, crop_xy=51.2),
    "av2": ICPFlowConfig.preset("av2"),
    "uniform": ICPFlowConfig.preset("av2"),
}
STREAM_REGIMES = ("pairwise", "streamed", "overlapped", "given")
#: metres of each scan's origin above the ground (KITTI's velodyne frame; the AV2 ego frame is the model's own)
SENSOR_HEIGHTS = {"kitti": 1.73, "av2": None}
#: scans of the shipped KITTI and AV2 streams as the ``cli`` mode plays them (KITTI's six back and forth, AV2's two
#: alternating): 20 timed frames a run (``--frames``)
CLI_SCANS = 26
#: each mode's options and their defaults (None: no default); an option of another mode is refused
MODES = {
    "pair": {
        "model": "fastflow3d_small", "decoder": None, "set": [], "device": "cpu", "threads": 2, "runs": 20,
        "warmup": 3, "scans": "kitti,av2", "points": 80_000, "regimes": "given,estimated",
        "backends": "onnx,onnx-tuned,openvino,eager", "breakdown": False,
    },
    "stream": {
        "model": "fastflow3d_small", "decoder": None, "set": [], "device": "cpu", "threads": 2,
        "scans": "kitti,av2", "passes": 5, "regimes": "pairwise,streamed,given", "backends": "onnx-tuned,openvino",
    },
    "refine": {"export": None, "runs": 20, "warmup": 3, "scans": "kitti,av2"},
    "cli": {
        "export": None, "device": "cpu", "threads": 0, "passes": 3, "scans": "kitti,av2,synthetic",
        "backends": "default", "frames": CLI_SCANS,
    },
}  # fmt: skip


def model_config(name: str, overrides: list[str]) -> dict:
    """``conf/model/<name>.yaml`` as train.py composes it, with ``model.<key>=<value>`` overrides."""
    cfg = compose("train", [f"model={name}", *(f"model.{item}" for item in overrides)])
    return OmegaConf.to_container(cfg.model, resolve=True)


def build_model(args):
    """(the random-weight student of ``--model``, ``--decoder`` and ``--set``, the overrides applied)."""
    overrides = ([f"decoder={args.decoder}"] if args.decoder else []) + list(args.set)
    return build_student(model_config(args.model, overrides)).eval(), overrides


def export_formats(backends) -> list[str]:
    """The export files ``backends`` run from: ``onnx`` (ONNX Runtime and OpenVINO), ``pt2``; none for eager."""
    return [f for f in ("onnx", "pt2") if any(b.startswith(f) or (f == "onnx" and "openvino" in b) for b in backends)]


def synthetic_calibration(model, pairs: int = 4) -> list[tuple[np.ndarray, np.ndarray]]:
    """The network inputs of ``pairs`` synthetic validation pairs (the world's ego motion and ground, the synthetic
    frame, ground removed, cropped to ``model``'s grid): the activation ranges of ``onnx-int8``'s random network."""
    contract = InputContract(Preprocessing(), True, model.grid)
    dataset = SyntheticDataset(split="val", num_sequences=pairs, frames_per_sequence=2)
    prepared = (
        contract.prepare(p.pc0, p.pc1, p.ego1_from_ego0, p.ground0, p.ground1) for p in map(dataset.pair, range(pairs))
    )
    return [(pair.network0, pair.network1) for pair in prepared]


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
    if name == "onnx-int8":
        int8_file = export_dir / INT8_FILE_NAME
        if not int8_file.is_file():
            write_int8(onnx_file, int8_file, synthetic_calibration(model))
        return load_network(int8_file, "onnx", runtime="onnxruntime", threads=threads, precision="int8")
    if name.startswith("openvino"):
        try:
            import openvino  # noqa: F401
        except ImportError:
            return None
        precision = "bf16" if name.endswith("bf16") else "f32"
        return load_network(onnx_file, "onnx", runtime="openvino", threads=threads, precision=precision)
    return load_network(onnx_file, "onnx", runtime="onnxruntime", threads=threads)


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


def pair(args) -> None:
    """The ``pair`` mode (see the module's docstring)."""
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    unknown = sorted(set(backends) - set(BACKENDS))
    if unknown or not backends:
        raise SystemExit(
            f"bench_student_latency: --backends: unknown {', '.join(unknown) or '(none)'}; use {', '.join(BACKENDS)}"
        )
    torch.set_num_threads(args.threads)
    model, overrides = build_model(args)
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
            tolerance = float("inf") if name == "onnx-int8" else tolerance  # int8's gate: trained, labelled pairs
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
            data = read_scan_pair(scan, args.points)
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
        def timed_call(*args, **kwargs):
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                self.spent[key] += time.perf_counter() - start

        return timed_call

    def take(self) -> dict[str, float]:
        spent, self.spent = self.spent, dict.fromkeys(self.spent, 0.0)
        return spent


def stream(args) -> None:
    """The ``stream`` mode (see the module's docstring)."""
    backends = [b.strip() for b in args.backends.split(",") if b.strip()]
    regimes = [r.strip() for r in args.regimes.split(",") if r.strip()]
    unknown = sorted(set(backends) - set(BACKENDS)) + sorted(set(regimes) - set(STREAM_REGIMES))
    if unknown or not backends or not regimes:
        raise SystemExit(
            f"bench_student_latency: unknown {', '.join(unknown) or '(none)'}; backends {BACKENDS}, {STREAM_REGIMES}"
        )
    torch.set_num_threads(args.threads)
    model, overrides = build_model(args)
    gpu = f", {torch.cuda.get_device_name()}, torch {torch.__version__}" if args.device == "cuda" else ""
    print(
        f"model {args.model}{''.join(' ' + item for item in overrides)} grid {model.grid.nx}x{model.grid.ny}; "
        f"network on {args.device}{gpu}; {cpu_name()}, {os.cpu_count()} logical CPUs, "
        f"{len(os.sched_getaffinity(0))} usable, {args.threads} threads; load average at start "
        f"{os.getloadavg()[0]:.2f}"
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
    if "overlapped" in times:  # FlowStream(overlap=True): a push returns the step before; per push = per frame
        for _ in range(passes):
            stream = FlowStream(Predictor(network, contract, backend), overlap=True)
            for k, scan in enumerate(scans):
                start = time.perf_counter()
                stream.push(scan)
                if k > 2:
                    times["overlapped"].append(time.perf_counter() - start)
            stream.flush()
    medians = {key: statistics.median(step[key] for step in per_step) for key in per_step[0]} if per_step else {}
    return times, memory, medians


def scan_calls(export: str, scan: str, pc0: np.ndarray, pc1: np.ndarray):
    """({method: call}, note on the refinement) for one scan pair; ego motion and ground masks computed once."""
    preprocessing = {"remove_ground": True, "teacher": TEACHERS[scan].to_dict()}
    options = {"preprocessing": preprocessing, "sensor_height": SENSOR_HEIGHTS[scan], "precision": "f32"}
    student = Predictor.load(export, **options)
    refined = Predictor.load(export, **options, refine=True)
    estimate = student.predict(pc0, pc1)  # the given regime's inputs, outside the timing
    ego, g0, lift = estimate.ego1_from_ego0, estimate.ground0, estimate.lift
    g1 = student.ground_mask("ground1", lift_points(pc1, lift), None)
    teacher = ICPFlow(TEACHERS[scan])
    frame0, frame1, frame_ego = lift_points(pc0, lift), lift_points(pc1, lift), lift_transform(ego, lift)
    calls = {
        "student": lambda: student.predict(pc0, pc1, ego, g0, g1),
        "student+refine": lambda: refined.predict(pc0, pc1, ego, g0, g1),
        "teacher": lambda: teacher(frame0, frame1, frame_ego, g0, g1),
    }
    plain, better = calls["student"](), calls["student+refine"]()
    change = np.linalg.norm(better.flow - plain.flow, axis=1)[better.refined]
    note = f"{better.refined.sum() / max(1, better.in_grid.sum()):.1%} of the network's points refined"
    return calls, note + (f", median change {np.median(change):.3f} m" if len(change) else "")


def refine(args) -> None:
    """The ``refine`` mode (see the module's docstring)."""
    rows = []
    for scan in [s.strip() for s in args.scans.split(",") if s.strip()]:
        data = read_scan_pair(scan)
        if data is None:
            print(f"{scan}: no scans under ../shared/data; no rows")
            continue
        calls, note = scan_calls(args.export, scan, *data)
        for name, times in timed(calls, args.runs, args.warmup).items():
            rows.append((scan, len(data[0]), name, times, note if name == "student+refine" else ""))
    print("| scan | points pc0 | method | median ms | p90 ms | Hz | refinement |")
    print("|---|---|---|---|---|---|---|")
    for scan, points, name, times, note in rows:
        median, p90 = statistics.median(times), float(np.percentile(times, 90))
        print(f"| {scan} | {points} | {name} | {1000 * median:.1f} | {1000 * p90:.1f} | {1 / median:.1f} | {note} |")
    print(f"median and p90 of {args.runs} calls after {args.warmup}; load average {os.getloadavg()[0]:.2f}")


def cli_streams(names: list[str], folder: Path, frames: int = CLI_SCANS) -> dict[str, tuple[Path, list[str]]]:
    """{name: (folder of scans, the CLI options a user of that sensor gives)}: ``kitti`` (the six HDL-64E scans
    000000-000005 played forth and back, 0 1 .. 5 4 .. 0 1 .., ``frames`` of them, copied as they are, ``.bin``,
    ``--sensor-height 1.73``), ``av2`` (the two sweeps alternating, ``frames`` written as ``.npy``), ``synthetic``
    (the first sequence of the test split, 40 frames, written as ``.npy``); a stream whose data ../shared/data lacks
    is left out with a line saying so."""
    streams = {}
    for name in names:
        target = folder / name
        if name == "kitti":
            files = sorted((DATA / "kitti_hdl64_scans").glob("*.bin"))
            if len(files) < 6:
                print("kitti: no scans under ../shared/data; no rows")
                continue
            target.mkdir()
            cycle = files + files[-2:0:-1]  # 0 1 2 3 4 5 4 3 2 1, then again
            for k in range(frames):
                (target / f"{k:06d}.bin").write_bytes(cycle[k % len(cycle)].read_bytes())
            streams[name] = (target, ["--sensor-height", str(SENSOR_HEIGHTS["kitti"])])
            continue
        target.mkdir()
        if name == "av2":
            pair = read_scan_pair("av2")
            if pair is None:
                print("av2: no sweeps under ../shared/data; no rows")
                continue
            scans = [pair[k % 2] for k in range(frames)]
        else:
            split = ["split=test", "dataset.reader.num_sequences=1", "dataset.reader.frames_per_sequence=40"]
            dataset, _ = open_split(split)
            pairs = [dataset[index] for index in range(len(dataset))]
            scans = [pair.pc0 for pair in pairs] + [pairs[-1].pc1]
        for k, scan in enumerate(scans):
            np.save(target / f"{k:06d}.npy", np.asarray(scan, np.float32))
        streams[name] = (target, [])
    return streams


def network_alone(export: str, runtime: str, scans: Path, options: list[str], calls: int = 10) -> float | None:
    """Seconds (median of ``calls`` after 3) of the ``runtime`` network alone (``onnxruntime[-precision]``, or
    ``default``: ``auto``'s; None for another) on one thread, in this process, on the first pair of the stream in
    ``scans`` (``options``: its CLI options, ``--sensor-height`` read). The ``cli`` mode's calibration: hosts that
    report the same CPU name run it up to two times apart (``benchmarks.common.cpu_name``), and a frame's time is
    compared only beside it."""
    engine, _, precision = ("onnxruntime", "", "auto") if runtime == "default" else runtime.partition("-")
    if engine != "onnxruntime":
        return None
    height = float(options[options.index("--sensor-height") + 1]) if "--sensor-height" in options else None
    predictor = Predictor.load(export, runtime=engine, threads=1, precision=precision or "f32", sensor_height=height)
    first, second = sorted(path for path in scans.iterdir())[:2]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the height-frame lift of velodyne scans
        pc0, pc1 = read_raw_scan(first), read_raw_scan(second)
        lift = predictor.frame_lift(pc0)
        lifted = lift_points(pc0, lift), lift_points(pc1, lift)
        grounds = [predictor.scan_masks(name, points, None)[0] for name, points in zip(("pc0", "pc1"), lifted)]
    pair = predictor.network_input(lifted, np.eye(4), *grounds)
    return statistics.median(timed({"network": lambda: predictor.run_network(pair)}, calls, warmup=3)["network"])


def cli(args) -> None:
    """The ``cli`` mode: ``python -m fastflow3d.inference.cli EXPORT DIR --out OUT [--refine]`` as a user runs it,
    ``--passes`` whole runs per stream and setting; a frame's time is the time between the outputs of consecutive
    pairs (their files' modification times: reading, every step and writing included; process start, the first two
    pairs and the last ``STREAM_DEPTH``, written after the last scan was read, left out)."""
    rows, calibration = [], None
    with tempfile.TemporaryDirectory() as tmp:
        for name, (scans, options) in cli_streams(args.scans.split(","), Path(tmp), args.frames).items():
            if calibration is None:
                runtime = args.backends.split(",")[0]
                seconds = network_alone(args.export, runtime, scans, options)
                calibration = "" if seconds is None else f"; {runtime} network alone {1000 * seconds:.1f} ms ({name})"
            for runtime, refine in itertools.product(args.backends.split(","), (False, True)):
                times = []
                for run in range(args.passes):
                    out = Path(tmp) / f"out_{name}_{runtime}_{refine}_{run}"
                    command = [sys.executable, "-m", "fastflow3d.inference.cli", args.export, str(scans)]
                    command += ["--out", str(out), *options]
                    command += ["--threads", str(args.threads)] if args.threads else []
                    if runtime == "pt2":  # the torch.export program, on --device
                        command += ["--backend", "pt2", "--device", args.device]
                    elif runtime != "default":  # default: the command a user types
                        # onnxruntime-int8: --precision int8. ONNX Runtime is the CLI's default engine: named only
                        # where a user would name it (before issue 44's twelfth session the default ignored --threads,
                        # and the bench, which named it, had not timed the command a user types)
                        engine, _, precision = runtime.partition("-")
                        command += [] if engine == "onnxruntime" else ["--runtime", engine]
                        command += ["--precision", precision or "f32"]
                    done = subprocess.run(command + (["--refine"] if refine else []), capture_output=True, text=True)
                    if done.returncode != 0:
                        said = (done.stderr.strip().splitlines() or ["(nothing on stderr)"])[-1]
                        raise SystemExit(f"bench_student_latency: {' '.join(command)} failed: {said}")
                    flows = sorted(out.glob("*.npz"), key=lambda path: path.stem)  # the scans' names: 000000, ...
                    written = np.array([path.stat().st_mtime_ns for path in flows]) / 1e9
                    # the last STREAM_DEPTH flows are written after the last scan was read (the pairs in flight): no
                    # frame's steps between them, so they are left out with the first two
                    times.extend(np.diff(written)[2:-STREAM_DEPTH])
                if runtime == "default":  # what --precision auto chose (the manifest names a precision but f32)
                    chosen = json.loads((out / MANIFEST).read_text())["options"].get("precision", "f32")
                label = f"default ({chosen})" if runtime == "default" else runtime
                rows.append((name, len(flows) + 1, label, refine, times))
    print("| stream | scans | runtime | refinement | median ms | p90 ms | Hz (median) | Hz (p90) |")
    print("|---|---|---|---|---|---|---|---|")
    for name, scans, runtime, refine, times in rows:
        median, p90 = statistics.median(times), float(np.percentile(times, 90))
        print(
            f"| {name} | {scans} | {runtime} | {'yes' if refine else 'no'} | {1000 * median:.1f} | {1000 * p90:.1f} "
            f"| {1 / median:.1f} | {1 / p90:.1f} |"
        )
    gpu = f"; pt2 on {torch.cuda.get_device_name()}" if args.device == "cuda" else ""
    threads = f"{args.threads} threads" if args.threads else "the CLI's threads"
    print(
        f"{args.passes} runs each, {threads}, {available_cores()} usable CPUs{gpu}; "
        f"load average {os.getloadavg()[0]:.2f}; {cpu_name()}{calibration or ''}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", choices=tuple(MODES), default="pair", help="what is timed (default pair)")
    parser.add_argument("--model", help="a conf/model option (default fastflow3d_small: CPU recipes; pair, stream)")
    parser.add_argument("--decoder", help="the model's decoder, a model.decoder override (pair, stream)")
    parser.add_argument("--set", nargs="*", metavar="KEY=VALUE", help="more model.<key> overrides (pair, stream)")
    parser.add_argument("--export", help="a trained student's export directory (or .ckpt) (refine, cli)")
    parser.add_argument("--device", choices=("cpu", "cuda"), help="where the network runs (pair, stream; cli: pt2)")
    parser.add_argument(
        "--threads", type=int, help="torch, ONNX Runtime and OpenVINO threads (default 2; cli: the CLI's default)"
    )
    parser.add_argument("--runs", type=int, help="timed calls (default 20; pair, refine)")
    parser.add_argument("--warmup", type=int, help="calls before (default 3; pair, refine)")
    parser.add_argument(
        "--passes", type=int, help="passes over each stream (default 5; stream) / runs of the CLI (default 3; cli)"
    )
    parser.add_argument(
        "--scans", help="comma-separated: kitti, av2 (default both), uniform (pair), synthetic (cli; default all three)"
    )
    parser.add_argument("--points", type=int, help="points per scan of the uniform scans (default 80000; pair)")
    parser.add_argument(
        "--regimes", help="comma-separated: given, estimated (pair); pairwise, streamed, given (stream); default all"
    )
    parser.add_argument(
        "--backends",
        help="comma-separated (default onnx,onnx-tuned,openvino,eager; stream: onnx-tuned,openvino; cli: the CLI's "
        "--runtime, onnxruntime and/or openvino, with -int8 / -bf16 for its --precision, or pt2: the export's "
        "torch.export program on --device; or default: the CLI's own choice; default default)",
    )
    parser.add_argument("--breakdown", action="store_true", default=None, help="time each step of a call (pair)")
    parser.add_argument("--frames", type=int, help=f"scans of the KITTI and AV2 streams (default {CLI_SCANS}; cli)")
    args = parser.parse_args()
    defaults = MODES[args.mode]
    for name, value in vars(args).items():
        if name == "mode":
            continue
        if name not in defaults:
            if value is not None:
                parser.error(f"--{name} is not an option of --mode {args.mode}")
        elif value is None:
            setattr(args, name, defaults[name])
    least = 5 + STREAM_DEPTH  # scans for one timed interval: the first two and the last STREAM_DEPTH are not timed
    if args.mode == "cli" and args.frames < least:
        parser.error(f"--frames must be at least {least} (one timed frame), got {args.frames}")
    if args.mode in ("refine", "cli") and args.export is None:
        parser.error(f"--mode {args.mode} needs --export (a trained student's export directory)")
    if getattr(args, "device", None) == "cuda" and not torch.cuda.is_available():
        raise SystemExit("bench_student_latency: --device cuda but torch sees no CUDA device (a CPU build of torch?)")
    {"pair": pair, "stream": stream, "refine": refine, "cli": cli}[args.mode](args)


if __name__ == "__main__":
    main()
