"""Labelling throughput with 1 and 2 workers, and shard size / read speed per compression.

    .venv/bin/python -m benchmarks.bench_label [--repeats 3] [--samples 8] [--shard-size 2] [--pinned] [overrides...]

Labels the first ``samples`` samples of the default synthetic world (conf/label.yaml; extra arguments are Hydra
overrides such as ``dataset.reader.beams=32``) into a temporary folder with 1 and then 2 local workers; samples/s
is the median over ``repeats`` runs of the whole ``label.py`` command, as a user runs it (interpreter start,
worker start, reader, teacher, writes: use enough samples that the start-up is amortised), and steady-state
(workers / the run's mean seconds per sample per worker, i.e. what a long run approaches). Then the
shards of one run are rewritten with each compression (same samples, same index): bytes per sample, and samples/s
and MB/s (of uncompressed arrays) reading every sample back through ``ShardDataset`` (median of ``repeats`` passes,
files reopened each pass).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np

from benchmarks.common import ROOT, compose
from icpflow.labelling.cli import label
from icpflow.shards import ShardDataset, verify_shard, write_shard
from icpflow.shards.schema import COMPRESSIONS


def labelling_rate(overrides: list[str], workers: int, repeats: int, cores: str | None = None) -> tuple[float, float]:
    """Median samples/s of ``label.py`` runs with ``workers`` processes: of the whole command, and steady-state
    (``workers`` over the summary's mean seconds per sample per worker, i.e. without start-up). ``cores``: run the
    command under ``taskset -c cores`` (label.py then sizes its threads to that affinity)."""
    rates, steady = [], []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as tmp:
            command = (["taskset", "-c", cores] if cores else []) + [
                sys.executable,
                str(ROOT / "label.py"),
                *overrides,
                f"out_dir={tmp}/labels",
                f"workers={workers}",
                f"hydra.run.dir={tmp}/hydra",
            ]
            start = time.perf_counter()
            run = subprocess.run(command, capture_output=True, text=True)
            seconds = time.perf_counter() - start
            if run.returncode:
                raise SystemExit(f"labelling failed: {run.stderr.strip().splitlines()[-1]}")
            index = json.loads((Path(tmp) / "labels" / "index.json").read_text())
            rates.append(sum(len(shard["samples"]) for shard in index["shards"]) / seconds)
            per_sample = float(re.search(r"mean ([0-9.]+) s/sample per worker", run.stdout).group(1))
            steady.append(workers / per_sample)
    return statistics.median(rates), statistics.median(steady)


def _shard_samples(path: Path) -> tuple[list[dict], str, str]:
    """The samples of a shard as ``write_shard`` takes them, its config text and config hash."""
    with h5py.File(path, "r") as f:
        samples = [
            {**{key: np.asarray(value[()]) for key, value in group.items()}, "attrs": dict(group.attrs)}
            for _, group in sorted(f["samples"].items())
        ]
        return samples, str(f.attrs["config"]), str(f.attrs["config_hash"])


def read_rate(out_dir: Path, repeats: int) -> tuple[float, int]:
    """Median seconds to read every sample of ``out_dir`` through ``ShardDataset``, and the bytes read."""
    times, size = [], 0
    for _ in range(repeats):
        reader = ShardDataset(out_dir)
        start = time.perf_counter()
        samples = [reader[i] for i in range(len(reader))]
        times.append(time.perf_counter() - start)
        reader.close()
        size = sum(v.nbytes for s in samples for v in s.values() if isinstance(v, np.ndarray))
    return statistics.median(times), size


def compression_rows(overrides: list[str], repeats: int) -> list[tuple]:
    """(compression, bytes/sample, read samples/s, read MB/s) for each compression setting."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        source = Path(tmp) / "labels"
        with contextlib.redirect_stdout(io.StringIO()):  # the summary line; errors still reach stderr
            status = label(compose("label", [*overrides, f"out_dir={source}", "workers=2"]), progress=False)
        if status:
            raise SystemExit("labelling failed")
        index = json.loads((source / "index.json").read_text())
        count = sum(len(shard["samples"]) for shard in index["shards"])
        for compression in COMPRESSIONS:
            out = Path(tmp) / compression
            out.mkdir()
            for shard in index["shards"]:
                samples, config, config_hash = _shard_samples(source / shard["file"])
                write_shard(out / shard["file"], samples, config, config_hash, compression)
                verify_shard(out / shard["file"], config_hash, len(samples))
            shutil.copy(source / "index.json", out / "index.json")
            size = sum((out / shard["file"]).stat().st_size for shard in index["shards"])
            seconds, raw = read_rate(out, repeats)
            rows.append((compression, size / count, count / seconds, raw / seconds / 1e6))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--samples", type=int, default=8)
    parser.add_argument("--shard-size", type=int, default=2)
    parser.add_argument(
        "--pinned",
        action="store_true",
        help="also time 1 worker pinned to one core (taskset -c 0): the per-core scaling of workers",
    )
    args, extra = parser.parse_known_args()
    overrides = [f"limit={args.samples}", f"shard_size={args.shard_size}", *extra]
    rows = {"1": labelling_rate(overrides, 1, args.repeats)}
    if args.pinned:
        rows["1 (one core)"] = labelling_rate(overrides, 1, args.repeats, cores="0")
    rows["2"] = labelling_rate(overrides, 2, args.repeats)
    print(f"labelling {args.samples} samples, shard_size {args.shard_size}, overrides {extra or 'none'}")
    print(f"{'workers':>13} {'samples/s (command)':>20} {'samples/s (steady)':>19}")
    for workers, (whole, steady) in rows.items():
        print(f"{workers:>13} {whole:>20.3f} {steady:>19.3f}")
    for base in rows:
        if base != "2":
            print(
                f"ratio 2 / {base}: {rows['2'][0] / rows[base][0]:.2f} (command), "
                f"{rows['2'][1] / rows[base][1]:.2f} (steady) (target >= 1.8)"
            )
    print(f"\n{'compression':<12} {'kB/sample':>10} {'read samples/s':>15} {'read MB/s':>10}")
    for name, size, rate, mbps in compression_rows(overrides, args.repeats):
        print(f"{name:<12} {size / 1e3:>10.1f} {rate:>15.1f} {mbps:>10.1f}")


if __name__ == "__main__":
    main()
