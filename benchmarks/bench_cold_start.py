"""A first labelling run (cold numba cache) against a rerun (warm cache), side by side, as a user runs label.py.

    .venv/bin/python benchmarks/bench_cold_start.py [--samples 4] [--workers 2] [overrides...]

Runs ``label.py`` on the first ``samples`` synthetic samples twice into fresh folders: first with an empty
``NUMBA_CACHE_DIR`` (a new environment: the teacher's kernels are not compiled yet), then with that same folder,
now filled (every later run). Prints, per run, the mean seconds per sample per worker (label.py's summary line:
reader + teacher inside a worker), the wall time of the whole command, and the lines label.py printed about
compiling; then the ratio cold / warm. Extra arguments are Hydra overrides for both runs.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SUMMARY = re.compile(r"mean ([0-9.]+) s/sample per worker")


def label_run(cache: Path, out_dir: Path, samples: int, workers: int, overrides: list[str]) -> dict:
    """One ``label.py`` command with ``NUMBA_CACHE_DIR=cache``: its s/sample per worker, wall time and messages."""
    command = [
        sys.executable,
        "label.py",
        f"limit={samples}",
        f"workers={workers}",
        "shard_size=1",
        f"out_dir={out_dir}",
        f"+hydra_dir={out_dir}/hydra",
        *overrides,
    ]
    start = time.perf_counter()
    done = subprocess.run(
        command, cwd=ROOT, env={**os.environ, "NUMBA_CACHE_DIR": str(cache)}, capture_output=True, text=True
    )
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"label.py failed ({done.returncode}): {done.stderr.strip().splitlines()[-1:]}")
    match = SUMMARY.search(done.stdout)
    messages = [line for line in done.stderr.splitlines() if "compil" in line]
    return {"per_sample": float(match.group(1)), "wall": wall, "messages": messages}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2)
    args, overrides = parser.parse_known_args()
    with tempfile.TemporaryDirectory() as tmp:
        cache = Path(tmp) / "numba_cache"
        cache.mkdir()
        runs = {}
        for name in ("cold", "warm"):
            runs[name] = label_run(cache, Path(tmp) / name, args.samples, args.workers, overrides)
    print(f"label.py limit={args.samples} workers={args.workers} {' '.join(overrides)}")
    print(f"{'cache':<6}| s/sample per worker | wall (s) | messages")
    for name, run in runs.items():
        print(f"{name:<6}| {run['per_sample']:>19.2f} | {run['wall']:>8.1f} | {' / '.join(run['messages']) or '-'}")
    ratio = runs["cold"]["per_sample"] / runs["warm"]["per_sample"]
    print(f"cold / warm: {ratio:.2f}x per sample, {runs['cold']['wall'] / runs['warm']['wall']:.2f}x wall")


if __name__ == "__main__":
    main()
