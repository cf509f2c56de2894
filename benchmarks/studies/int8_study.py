# Frozen study (issue 22), as of commit fc2e986; figures: BENCHMARKS.md, "Issue 22: real time on a laptop CPU" (int8).
"""Int8 inference of a trained student: speed and the accuracy it costs on the held-out test split.

    .venv/bin/python -m benchmarks.studies.int8_study --export <a train.py export folder> [--out outputs/int8]
        [--calibration-pairs 8] [--test-sequences 16] [--runs 10] [--threads 2]

The export's ``fastflow3d.onnx`` is quantised by ONNX Runtime's static quantisation (QDQ format, per-channel int8
weights of every Conv and Gemm, uint8 activations with ranges calibrated on ``--calibration-pairs`` synthetic
training pairs, non-ground points, pc0 ego-compensated as the Predictor feeds the network) after ONNX Runtime's own
graph fusion, and written beside a copy of the export's metadata (its file hash updated) as an export folder
``<out>/export_int8`` that eval.py and the Predictor load. Prints the network's latency in ONNX Runtime, float32 and
int8 taking turns (median of ``--runs`` after 3, ``--threads`` intra-op threads, the shipped real scans' points
above the ground), and the EPE of both on the synthetic test split (``eval.py split=test
dataset.reader.num_sequences=<test-sequences>``), with the change in per cent. Needs ../shared/data for the scans.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import time
from pathlib import Path

import numpy as np

from benchmarks.common import ROOT, read_scan_pair
from benchmarks.training_runs import run_python, scores
from fastflow3d.artifact.file_format import sha256_file
from fastflow3d.network.model import compensate
from icpflow.core.atomic import write_text_atomic
from icpflow.datasets.synthetic.reader import SyntheticDataset


def calibration_feeds(pairs: int) -> list[dict]:
    """The network's inputs for ``pairs`` synthetic training pairs: non-ground points, pc0 ego-compensated."""
    dataset = SyntheticDataset(split="train", num_sequences=pairs, frames_per_sequence=2)
    feeds = []
    for index in range(pairs):
        pair = dataset.pair(index)
        pc0 = compensate(pair.pc0[~pair.ground0], pair.ego1_from_ego0).astype(np.float32)
        feeds.append({"pc0_compensated": pc0, "pc1": pair.pc1[~pair.ground1].astype(np.float32)})
    return feeds


def quantised_export(export: Path, out: Path, feeds: list[dict]) -> Path:
    """``out/export_int8``: the export with its ONNX file fused by ONNX Runtime, then QDQ int8 (see docstring)."""
    import onnxruntime as ort
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, quantize_static

    class Feeds(CalibrationDataReader):
        def __init__(self):
            self.remaining = iter(feeds)

        def get_next(self):
            return next(self.remaining, None)

    fused = out / "fused.onnx"
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED
    options.optimized_model_filepath = str(fused)
    ort.InferenceSession(str(export / "fastflow3d.onnx"), options, providers=["CPUExecutionProvider"])
    target = out / "export_int8"
    shutil.rmtree(target, ignore_errors=True)
    target.mkdir(parents=True)
    quantize_static(
        str(fused), str(target / "fastflow3d.onnx"), Feeds(), quant_format=QuantFormat.QDQ, per_channel=True,
        op_types_to_quantize=["Conv", "Gemm"],
    )  # fmt: skip
    metadata = json.loads((export / "metadata.json").read_text())
    metadata["files"] = {"onnx": {"path": "fastflow3d.onnx", "sha256": sha256_file(target / "fastflow3d.onnx")}}
    write_text_atomic(target / "metadata.json", json.dumps(metadata, indent=2))
    return target


def latency(models: dict[str, Path], runs: int, threads: int) -> dict[str, dict[str, float]]:
    """Median network time (ms) per scan and model, the models taking turns."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    cpu = ["CPUExecutionProvider"]
    sessions = {name: ort.InferenceSession(str(path), options, providers=cpu) for name, path in models.items()}
    result = {}
    for scan in ("kitti", "av2"):
        scans = read_scan_pair(scan)
        if scans is None:
            continue
        ground_z = 0.3 if scan == "av2" else -1.4  # sensor frames: AV2's origin near the ground, KITTI's 1.73 m up
        pc0, pc1 = (s[s[:, 2] > ground_z] for s in scans)
        feeds = {"pc0_compensated": pc0, "pc1": pc1}
        times = {name: [] for name in sessions}
        for step in range(runs + 3):
            for name, session in sessions.items():
                tic = time.perf_counter()
                session.run(None, feeds)
                if step >= 3:
                    times[name].append(1000 * (time.perf_counter() - tic))
        result[scan] = {name: statistics.median(values) for name, values in times.items()}
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--export", type=Path, required=True, help="a train.py export folder (fastflow3d.onnx)")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "int8")
    parser.add_argument("--calibration-pairs", type=int, default=8)
    parser.add_argument("--test-sequences", type=int, default=16, help="test split sequences (4 pairs each)")
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    export, out = args.export.resolve(), args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    int8 = quantised_export(export, out, calibration_feeds(args.calibration_pairs))
    times = latency({"float32": export / "fastflow3d.onnx", "int8": int8 / "fastflow3d.onnx"}, args.runs, args.threads)
    test = ["split=test", f"dataset.reader.num_sequences={args.test_sequences}", "bev=0", "method=[student]"]
    epe = {}
    for name, folder in (("float32", export), ("int8", int8)):
        run_python(["eval.py", *test, f"checkpoint={folder}", f"out_dir={out / ('eval_' + name)}"])
        epe[name] = scores(out / f"eval_{name}" / "metrics.json", "student")
    print(f"\nNetwork latency, ONNX Runtime, {args.threads} threads, median of {args.runs} (ms):")
    print("| scan | float32 | int8 | speed-up |\n|---|---|---|---|")
    for scan, row in times.items():
        print(f"| {scan} | {row['float32']:.1f} | {row['int8']:.1f} | {row['float32'] / row['int8']:.2f}x |")
    print(f"\nEPE (m) on the test split ({4 * args.test_sequences} pairs):")
    print("| category | float32 | int8 | change |\n|---|---|---|---|")
    for key in epe["float32"]:
        a, b = epe["float32"][key], epe["int8"][key]
        print(f"| {key} | {a:.4f} | {b:.4f} | {100 * (b / a - 1):+.1f} % |")


if __name__ == "__main__":
    main()
