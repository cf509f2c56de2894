"""Labelling throughput with 1 and 2 workers, and shard size / read speed per compression.

    .venv/bin/python benchmarks/bench_label.py [--repeats 3] [--samples 8] [--shard-size 2] [hydra overrides...]

Labels the first ``samples`` samples of the default synthetic world (conf/label.yaml; extra arguments are Hydra
overrides such as ``dataset.reader.beams=32``) into a temporary folder with 1 and then 2 local workers; samples/s
is the median over ``repeats`` runs of the whole ``run_labelling`` call (process start, reader, teacher, writes).
Then the labelled samples are rewritten with each compression: bytes per sample, and samples/s and MB/s (of
uncompressed arrays) reading them back through ``ShardDataset`` (median of ``repeats`` passes, files reopened).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from hydra import compose, initialize_config_dir

from icpflow.labelling.cli import label
from icpflow.shards import ShardDataset, write_index, write_shard

CONF = Path(__file__).resolve().parents[1] / "conf"


def labelling_rate(overrides: list[str], workers: int, repeats: int) -> float:
    """Median samples/s of a full labelling run with ``workers`` processes."""
    rates = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as tmp, initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            cfg = compose("label", [*overrides, f"out_dir={tmp}", f"workers={workers}"])
            start = time.perf_counter()
            if label(cfg, progress=False):
                raise SystemExit("labelling failed")
            rates.append(cfg.limit / (time.perf_counter() - start))
    return statistics.median(rates)


def compression_rows(overrides: list[str], repeats: int) -> list[tuple]:
    """(compression, bytes/sample, read samples/s, read MB/s) for none, lzf and gzip."""
    rows = []
    with tempfile.TemporaryDirectory() as tmp, initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        source = Path(tmp) / "labels"
        if label(compose("label", [*overrides, f"out_dir={source}", "workers=2"]), progress=False):
            raise SystemExit("labelling failed")
        dataset = ShardDataset(source)
        samples = [dataset[i] for i in range(len(dataset))]
        raw = sum(v.nbytes for s in samples for v in s.values() if hasattr(v, "nbytes"))
        for compression in (None, "lzf", "gzip"):
            out = Path(tmp) / str(compression)
            out.mkdir()
            stored = [{**{k: v for k, v in s.items() if hasattr(v, "nbytes")},
                       "attrs": {"sample_id": s["sample_id"], "log_id": s["log_id"], "index": i, "timestamp0_ns": -1,
                                 "timestamp1_ns": -1, "dt": s["dt"]}} for i, s in enumerate(samples)]
            write_shard(out / "shard_000000.h5", stored, "", "bench", compression)
            write_index(out / "index.json", {"config_hash": "bench", "shards": [
                {"file": "shard_000000.h5", "samples": [{"index": i} for i in range(len(stored))]}]})
            size = (out / "shard_000000.h5").stat().st_size
            times = []
            for _ in range(repeats):
                reader = ShardDataset(out)
                start = time.perf_counter()
                for i in range(len(reader)):
                    reader[i]
                times.append(time.perf_counter() - start)
                reader.close()
            seconds = statistics.median(times)
            rows.append((compression or "none", size / len(stored), len(stored) / seconds, raw / seconds / 1e6))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--samples", type=int, default=8)
    parser.add_argument("--shard-size", type=int, default=2)
    args, extra = parser.parse_known_args()
    overrides = [f"limit={args.samples}", f"shard_size={args.shard_size}", *extra]
    one = labelling_rate(overrides, 1, args.repeats)
    two = labelling_rate(overrides, 2, args.repeats)
    print(f"labelling {args.samples} samples, shard_size {args.shard_size}, overrides {extra or 'none'}")
    print(f"{'workers':>8} {'samples/s':>10}")
    print(f"{1:>8} {one:>10.3f}\n{2:>8} {two:>10.3f}\nratio 2/1: {two / one:.2f}")
    print(f"\n{'compression':<12} {'kB/sample':>10} {'read samples/s':>15} {'read MB/s':>10}")
    for name, size, rate, mbps in compression_rows(overrides, args.repeats):
        print(f"{name:<12} {size / 1e3:>10.1f} {rate:>15.1f} {mbps:>10.1f}")


if __name__ == "__main__":
    main()
