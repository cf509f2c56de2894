"""Steps per minute of the student's training loop as ``train.py`` runs it: two (or more) source trees side by side.

Each run is a subprocess ``<tree>/.venv/bin/python train.py`` in that tree (its own code and configs) on the same
shards, with validation and export off and ``benchmarks.step_timer`` recording the end of every step. A run's
figure is taken after ``--warmup`` steps (DataLoader start, first allocations): the median step time and the mean
(time of the last step minus that of the warm-up step, over the steps between), steps per minute = 60 / mean. Runs
alternate (A, B, A, B, ...) ``--repeats`` times, so a change of machine load hits both; the table gives each run's
median over the repeats and the ratio to the first run.

Usage:
  python -m benchmarks.bench_training_step --train /work/data/labels/train16 --val /work/data/labels/val \\
      --run before=/work/wt/i19-base --run after=. [--run "after-w2=.:data.workers=2"] [--steps 40] [--warmup 10]
A run is NAME=TREE[:override,override,...] (Hydra overrides added to that tree's train.py command line; an item
``env:NAME=VALUE`` sets an environment variable of the run instead, e.g. ``env:OMP_NUM_THREADS=1``).

``--work N`` first prints the CPU work of a step in each run's tree (``benchmarks.student_step_work``: one
thread, process time, median of N batches), which holds on a loaded machine where wall-clock step times do not.

The two helpers run inside each tree's process, found through ``PYTHONPATH=<this checkout>`` (after the tree's
own code, which comes first: ``train.py``'s folder, ``-m``'s working directory).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import ROOT, split_overrides

#: a run's environment: this checkout's ``benchmarks`` importable in the tree's process
HELPERS = {"PYTHONPATH": str(ROOT)}


def parse_run(text: str) -> tuple[str, Path, list[str]]:
    """``NAME=TREE[:override,...]`` -> (name, tree, overrides)."""
    name, _, rest = text.partition("=")
    tree, _, extra = rest.partition(":")
    if not name or not tree:
        raise SystemExit(f"bench_training_step: --run {text!r}: expected NAME=TREE[:override,...]")
    return name, Path(tree).resolve(), split_overrides(extra)


def split_env(items: list[str]) -> tuple[list[str], dict[str, str]]:
    """Hydra overrides and ``env:NAME=VALUE`` items -> (overrides, environment variables)."""
    overrides = [item for item in items if not item.startswith("env:")]
    env = dict(item[len("env:") :].split("=", 1) for item in items if item.startswith("env:"))
    return overrides, env


def run_once(tree: Path, items: list[str], args, out: Path) -> dict:
    """One ``train.py`` run in ``tree``; returns its step-time figures (seconds)."""
    overrides, run_env = split_env(items)
    timer = out / "steps.json"
    command = [
        str(tree / ".venv" / "bin" / "python"),
        "train.py",
        f"data.train={args.train}",
        f"data.val={args.val}",
        f"out_dir={out}",
        f"trainer.max_steps={args.steps}",
        "+trainer.limit_val_batches=0",
        "trainer.num_sanity_val_steps=0",
        "export.formats=[]",
        "+callbacks.step_timer._target_=benchmarks.step_timer.StepTimer",
        f"+callbacks.step_timer.path={timer}",
        *args.common,
        *overrides,
    ]
    env = {**os.environ, **run_env, **HELPERS}
    start = time.perf_counter()
    done = subprocess.run(command, cwd=tree, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0 or not timer.is_file():
        raise SystemExit(f"bench_training_step: run in {tree} failed:\n{done.stderr[-3000:]}")
    ends = json.loads(timer.read_text())["ends"]
    steps = ends[args.warmup - 1 :]
    gaps = [b - a for a, b in zip(steps[:-1], steps[1:])]
    return {"median": statistics.median(gaps), "mean": (steps[-1] - steps[0]) / len(gaps), "wall": wall}


def step_work(tree: Path, items: list[str], args) -> dict:
    """CPU seconds of one step's network work and of one sample's loading in ``tree`` (one thread)."""
    overrides, _ = split_env(items)
    command = [
        str(tree / ".venv" / "bin" / "python"),
        "-m",
        "benchmarks.student_step_work",
        str(tree / "conf"),
        str(Path(args.train).resolve()),
        str(Path(args.val).resolve()),
        str(args.work),
        *args.common,
        *overrides,
    ]
    done = subprocess.run(command, cwd=tree, env={**os.environ, **HELPERS}, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"bench_training_step: step work in {tree} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", required=True, help="labelled shard directory (data.train)")
    parser.add_argument("--val", required=True, help="labelled shard directory (data.val; not run, but checked)")
    parser.add_argument("--run", action="append", required=True, help="NAME=TREE[:override,...]; first = reference")
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--common", nargs="*", default=[], help="overrides for every run")
    parser.add_argument("--work", type=int, default=0, help="also the CPU work per step, median of N batches")
    parser.add_argument("--no-loop", action="store_true", help="only --work, no train.py runs")
    args = parser.parse_args()
    if args.steps - args.warmup < 10:
        raise SystemExit("bench_training_step: need >= 10 timed steps (--steps - --warmup)")
    runs = [parse_run(text) for text in args.run]
    if args.work:
        print(f"CPU work per training step, one thread, process time, median of {args.work} batches")
        print("| run | network step (CPU s) | loading per sample (CPU s) | step + batch loading (CPU s) | ratio |")
        print("|---|---|---|---|---|")
        reference = None
        for name, tree, overrides in runs:
            work = step_work(tree, overrides, args)
            total = work["step"] + work["batch"] * work["sample"]
            reference = reference or total
            print(f"| {name} | {work['step']:.3f} | {work['sample']:.4f} | {total:.3f} | {reference / total:.2f}x |")
    if args.no_loop:
        return
    figures: dict[str, list[dict]] = {name: [] for name, _, _ in runs}
    with tempfile.TemporaryDirectory(prefix="bench_training_step_") as scratch:
        for repeat in range(args.repeats):
            for name, tree, overrides in runs:
                result = run_once(tree, overrides, args, Path(scratch) / f"{name}-{repeat}")
                figures[name].append(result)
                print(
                    f"# {name} repeat {repeat}: median {result['median']:.3f} s, mean {result['mean']:.3f} s/step, "
                    f"process {result['wall']:.0f} s; load {os.getloadavg()[0]:.1f}",
                    file=sys.stderr,
                )
    timed = args.steps - args.warmup
    print(
        f"train.py on {args.train}, steps {args.warmup + 1}-{args.steps} timed ({timed} steps), "
        f"{args.repeats} alternating repeats (median over repeats); load average at the end {os.getloadavg()[0]:.1f}"
    )
    print("| run | tree and overrides | median s/step | mean s/step | steps per minute | speed-up (mean) |")
    print("|---|---|---|---|---|---|")
    reference = None
    for name, tree, overrides in runs:
        median = statistics.median(f["median"] for f in figures[name])
        mean = statistics.median(f["mean"] for f in figures[name])
        reference = reference or mean
        what = f"{tree.name} {' '.join(overrides)}".strip()
        print(f"| {name} | {what} | {median:.3f} | {mean:.3f} | {60 / mean:.0f} | {reference / mean:.2f}x |")


if __name__ == "__main__":
    main()
