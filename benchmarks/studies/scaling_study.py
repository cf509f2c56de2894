# Frozen study (issue 13), as of commit 0beb838; figures and scaling.png: BENCHMARKS.md, "Data-scaling study".
"""Data-scaling study of the student: dynamic-foreground EPE on the synthetic test split against the number of
labelled training pairs, for pseudo-label (distillation) and ground-truth (supervised) training, with the teacher
and ego-only flow on the same test pairs as reference lines.

    .venv/bin/python -m benchmarks.studies.scaling_study [--sizes 16,64,256] [--supervision pseudo,gt] [--steps 600]
        [--test-sequences 16] [--experiment synthetic_cpu] [--out outputs/scaling]

Every stage is the project's own command line, run as a subprocess: ``label.py`` (sizes/2 independent sequences of
3 frames, so each size holds size pairs; the val split as usual), ``train.py experiment=<experiment>`` with the same
steps for every size (checkpoint chosen on val), ``eval.py split=test`` (teacher and ego-only once, then each
student). A stage whose output exists is skipped, so an interrupted study resumes. Prints a Markdown table and
writes ``scaling.png`` and ``scaling.json`` under ``--out``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from benchmarks.common import ROOT
from benchmarks.training_runs import run_python, save_line_plot, scores, trained_and_scored
from icpflow.core.atomic import write_text_atomic
from icpflow.evaluation import is_complete

SUPERVISION = {"pseudo": "distillation", "gt": "supervised"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="16,64,256", help="labelled training pairs, comma-separated (even)")
    parser.add_argument("--supervision", default="pseudo,gt", help="pseudo (teacher labels) and/or gt")
    parser.add_argument("--steps", type=int, default=600, help="optimiser steps of every training run")
    parser.add_argument("--test-sequences", type=int, default=16, help="test split sequences (4 pairs each)")
    parser.add_argument("--experiment", default="synthetic_cpu")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "scaling")
    args = parser.parse_args()
    sizes = [int(s) for s in args.sizes.split(",")]
    supervisions = [s.strip() for s in args.supervision.split(",")]
    if any(size < 2 or size % 2 for size in sizes) or any(s not in SUPERVISION for s in supervisions):
        parser.error("sizes must be even numbers >= 2, supervision pseudo and/or gt")
    out = args.out.resolve()
    test = ["split=test", f"dataset.reader.num_sequences={args.test_sequences}", "bev=0"]

    val = out / "labels" / "val"
    if not (val / "index.json").is_file():
        run_python(["label.py", "split=val", f"out_dir={val}"])
    baselines = out / "eval" / "baselines" / "metrics.json"
    if not is_complete(baselines):
        run_python(["eval.py", *test, "method=[ego,icpflow]", f"out_dir={baselines.parent}"])
    teacher, ego = scores(baselines, "icpflow"), scores(baselines, "ego")

    rows = []
    for size in sizes:
        labels = out / "labels" / f"train{size}"
        if not (labels / "index.json").is_file():
            run_python(
                [
                    "label.py",
                    "split=train",
                    f"dataset.reader.num_sequences={size // 2}",
                    "dataset.reader.frames_per_sequence=3",
                    f"out_dir={labels}",
                ]
            )
        for supervision in supervisions:
            name = f"{supervision}{size}"
            train = [
                f"experiment={args.experiment}",
                f"data.train={labels}",
                f"data.val={val}",
                f"trainer.max_steps={args.steps}",
                f"loss.name={SUPERVISION[supervision]}",
            ]
            run_dir, metrics = out / "runs" / name, out / "eval" / name / "metrics.json"
            rows.append(
                {"pairs": size, "supervision": supervision, **trained_and_scored(run_dir, metrics, train, test)}
            )

    print(
        f"\nStudent on the synthetic test split ({args.test_sequences * 4} pairs), {args.steps} steps of "
        f"experiment={args.experiment}; teacher {teacher['dynamic_fg']:.4f} m, ego-only {ego['dynamic_fg']:.4f} m "
        "dynamic-fg EPE"
    )
    print("| pairs | supervision | dynamic fg EPE (m) | x teacher | Threeway EPE (m) | training (s) |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        print(
            f"| {row['pairs']} | {row['supervision']} | {row['dynamic_fg']:.4f} | "
            f"{row['dynamic_fg'] / teacher['dynamic_fg']:.2f} | {row['threeway']:.4f} | {row['seconds']:.0f} |"
        )
    write_text_atomic(
        out / "scaling.json",
        json.dumps(
            {"rows": rows, "teacher": teacher, "ego": ego, "steps": args.steps, "experiment": args.experiment}, indent=2
        ),
    )
    curves = []
    for supervision, style in (("pseudo", "o-"), ("gt", "s--")):
        points = [(row["pairs"], row["dynamic_fg"]) for row in rows if row["supervision"] == supervision]
        if points:
            label = "pseudo-labels" if supervision == "pseudo" else "ground truth"
            curves.append((*zip(*points), style, f"student, {label}"))
    save_line_plot(
        out / "scaling.png",
        f"Student data scaling ({args.steps} steps each), dynamic foreground",
        "labelled training pairs",
        curves,
        [
            (teacher["dynamic_fg"], "green", ":", "teacher (ICP-Flow)"),
            (ego["dynamic_fg"], "grey", ":", "ego-only flow"),
        ],
    )


if __name__ == "__main__":
    main()
