"""Learning curves of student variants against CPU minutes (issue 43, point 2): which variant fits the labels
fastest on a CPU, and what it keeps on pairs it never saw.

    .venv/bin/python -m benchmarks.capacity_curves --run NAME=RUN_DIR:CPU_S [--run ...] [--fit-sequences 16]

Each ``--run`` is a ``train.py`` out_dir (a ``student_ablation`` run: its TensorBoard events, its ``score/`` on
the test split) and the CPU seconds one of its training steps costs (``python -m benchmarks.bench_training_step
... --work 5``: one thread, process time, batch loading included), which turns its steps into CPU minutes. Prints
per run, at each validation: CPU minutes, the mean training loss since the last validation (the fit to its
labels) and the validation dynamic-foreground EPE (pairs it never saw); then the end of each run: its steps and
CPU minutes, the test split's dynamic-foreground, static-foreground and Threeway EPE (``score/metrics.json``) and
its fit on its own training pairs: ``eval.py split=train dataset.reader.num_sequences=<--fit-sequences>
dataset.reader.frames_per_sequence=3`` (the first sequences of the synthetic training split: pairs of any
``label.py ... frames_per_sequence=3`` shards of at least that many sequences), scored into ``RUN_DIR/fit/``
(kept; reused), beside the teacher on the same pairs (the labels it learnt from; into the first run's
``fit_teacher/``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from benchmarks.student_anatomy import curve_points
from benchmarks.training_runs import evaluated, scores


def fit_scores(out_dir: Path, sequences: int, method: str, checkpoint: Path | None = None) -> dict:
    """``method`` (``student``: the export ``checkpoint``; ``icpflow``: the teacher, whose labels these pairs got)
    scored on the first ``sequences`` sequences of the training split (3 frames each), into ``out_dir``."""
    split = ["split=train", f"dataset.reader.num_sequences={sequences}", "dataset.reader.frames_per_sequence=3"]
    return evaluated(out_dir / "metrics.json", [*split, "bev=0"], method, checkpoint)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", action="append", required=True, help="NAME=RUN_DIR:CPU_SECONDS_PER_STEP")
    parser.add_argument("--fit-sequences", type=int, default=16, help="training sequences of the fit (3 frames)")
    args = parser.parse_args()
    runs = []
    for item in args.run:
        name, _, rest = item.partition("=")
        folder, _, seconds = rest.rpartition(":")
        runs.append((name, Path(folder), float(seconds)))
    print("| run | step | CPU minutes | training loss (mean since the last validation) | val dynamic EPE (m) |")
    print("|---|---|---|---|---|")
    ends = []
    for name, folder, seconds in runs:
        points = curve_points(folder)
        for step, (train_loss, _, val_epe) in sorted(points.items()):
            loss = "-" if train_loss is None else f"{train_loss:.4f}"
            print(f"| {name} | {step} | {step * seconds / 60:.1f} | {loss} | {val_epe:.4f} |")
        last = max(points)
        fit = fit_scores(folder / "fit", args.fit_sequences, "student", folder / "export")
        ends.append((name, last, last * seconds / 60, scores(folder / "score" / "metrics.json", "student"), fit))
    teacher = fit_scores(runs[0][1] / "fit_teacher", args.fit_sequences, "icpflow")
    print()
    print(
        "| run | steps | CPU minutes | test dynamic fg | test static fg | test Threeway | training pairs dynamic fg "
        "| training pairs Threeway | test / training pairs (dynamic) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for name, steps, minutes, test, fit in ends:
        print(
            f"| {name} | {steps} | {minutes:.1f} | {test['dynamic_fg']:.4f} | {test['static_fg']:.4f} | "
            f"{test['threeway']:.4f} | {fit['dynamic_fg']:.4f} | {fit['threeway']:.4f} | "
            f"{test['dynamic_fg'] / fit['dynamic_fg']:.2f} |"
        )
    print(
        f"| the teacher (its labels of the training pairs) | | | | | | {teacher['dynamic_fg']:.4f} | "
        f"{teacher['threeway']:.4f} | |"
    )


if __name__ == "__main__":
    main()
