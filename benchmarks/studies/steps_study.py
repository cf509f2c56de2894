# Frozen study (issue 19, point 4), as of commit 0beb838; figures and steps.png: BENCHMARKS.md, "Third session
# (2026-11-25, 20:10-23:10): how far steps carry (point 4)".
"""How far optimiser steps carry the student: the recipe trained at 1x, 2x and 4x its steps (each run with its own
warm-up and cosine schedule, as a user would run it), every run scored on the synthetic test split beside the
teacher and ego-only flow. Says whether the student is limited by CPU time or by its design.

    .venv/bin/python -m benchmarks.studies.steps_study --train <shards> --val <shards> [--steps 1400] [--factors 1,2,4]
        [--experiment synthetic_cpu] [--test-sequences 16] [--baselines <eval.py metrics.json with ego, icpflow>]
        [--out outputs/steps] [--override KEY=VALUE ...]

Every stage is the project's own command line, run as a subprocess (``train.py``, ``eval.py``); a stage whose
output exists is skipped, so an interrupted study resumes. Prints a Markdown table and writes ``steps.png`` and
``steps.json`` under ``--out``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from benchmarks.common import ROOT
from benchmarks.training_runs import run_python, save_line_plot, scores, trained_and_scored
from icpflow.core.atomic import write_text_atomic
from icpflow.evaluation import is_complete


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", type=Path, required=True, help="training shards (a label.py out_dir)")
    parser.add_argument("--val", type=Path, required=True, help="validation shards (checkpoint selection)")
    parser.add_argument("--steps", type=int, default=1400, help="the recipe's steps (1x)")
    parser.add_argument("--factors", default="1,2,4")
    parser.add_argument("--experiment", default="synthetic_cpu")
    parser.add_argument("--test-sequences", type=int, default=16, help="test split sequences (4 pairs each)")
    parser.add_argument("--baselines", type=Path, help="an eval.py metrics.json with ego and icpflow on that split")
    parser.add_argument("--override", action="append", default=[], help="further train.py overrides")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "steps")
    args = parser.parse_args()
    factors = [int(f) for f in args.factors.split(",")]
    out = args.out.resolve()
    test = ["split=test", f"dataset.reader.num_sequences={args.test_sequences}", "bev=0"]
    baselines = args.baselines or out / "eval" / "baselines" / "metrics.json"
    if not is_complete(baselines):
        run_python(["eval.py", *test, "method=[ego,icpflow]", f"out_dir={baselines.parent}"])
    teacher, ego = scores(baselines, "icpflow"), scores(baselines, "ego")
    rows = []
    for factor in factors:
        steps = factor * args.steps
        train = [
            f"experiment={args.experiment}",
            f"data.train={args.train.resolve()}",
            f"data.val={args.val.resolve()}",
            f"trainer.max_steps={steps}",
            *args.override,
        ]
        run_dir, metrics = out / "runs" / f"steps{steps}", out / "eval" / f"steps{steps}" / "metrics.json"
        rows.append({"factor": factor, "steps": steps, **trained_and_scored(run_dir, metrics, train, test)})

    print(
        f"\nStudent on the synthetic test split ({args.test_sequences * 4} pairs), experiment={args.experiment} "
        f"{' '.join(args.override)}; teacher dynamic fg {teacher['dynamic_fg']:.4f} m, "
        f"Threeway {teacher['threeway']:.4f}; ego-only dynamic fg {ego['dynamic_fg']:.4f} m"
    )
    print(
        "| steps | dynamic fg EPE (m) | x teacher | Threeway EPE (m) | x teacher | static fg EPE (m) | training (s) |"
    )
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        print(
            f"| {row['steps']} ({row['factor']}x) | {row['dynamic_fg']:.4f} "
            f"| {row['dynamic_fg'] / teacher['dynamic_fg']:.2f} "
            f"| {row['threeway']:.4f} | {row['threeway'] / teacher['threeway']:.2f} | {row['static_fg']:.4f} "
            f"| {row['seconds']:.0f} |"
        )
    write_text_atomic(
        out / "steps.json",
        json.dumps({"rows": rows, "teacher": teacher, "ego": ego, "experiment": args.experiment}, indent=2),
    )
    steps = [row["steps"] for row in rows]
    save_line_plot(
        out / "steps.png",
        f"Student vs steps ({args.experiment})",
        "optimiser steps (batch 4)",
        [
            (steps, [row["dynamic_fg"] for row in rows], "o-", "student, dynamic foreground"),
            (steps, [row["threeway"] for row in rows], "s--", "student, Threeway"),
        ],
        [
            (teacher["dynamic_fg"], "green", ":", "teacher, dynamic foreground"),
            (teacher["threeway"], "green", "-.", "teacher, Threeway"),
            (ego["dynamic_fg"], "grey", ":", "ego-only, dynamic foreground"),
        ],
    )


if __name__ == "__main__":
    main()
