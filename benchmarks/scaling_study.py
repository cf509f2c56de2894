"""Data-scaling study of the student: dynamic-foreground EPE on the synthetic test split against the number of
labelled training pairs, for pseudo-label (distillation) and ground-truth (supervised) training, with the teacher
and ego-only flow on the same test pairs as reference lines.

    .venv/bin/python benchmarks/scaling_study.py [--sizes 16,64,256] [--supervision pseudo,gt] [--steps 600]
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
import subprocess
import sys
import time
from pathlib import Path

from icpflow.atomic import atomic_path, write_text_atomic
from icpflow.evaluation import is_complete, method_summary, read_metrics

ROOT = Path(__file__).resolve().parents[1]
SUPERVISION = {"pseudo": "distillation", "gt": "supervised"}


def run(arguments: list[str]) -> float:
    """Run ``python <arguments>`` in the repository root; seconds taken (raises on a non-zero exit)."""
    tic = time.perf_counter()
    print("$ python " + " ".join(arguments), flush=True)
    subprocess.run([sys.executable, *arguments], cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - tic


def dynamic_epe(metrics_json: Path, method: str) -> tuple[float, float]:
    """(dynamic-foreground EPE, Threeway EPE) of ``method`` in an eval.py ``metrics.json``."""
    summary = method_summary(read_metrics(metrics_json), method)
    return summary["paper"]["point_weighted"]["dynamic_fg"]["EPE"], summary["threeway"]["threeway"]


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
        run(["label.py", "split=val", f"out_dir={val}"])
    baselines = out / "eval" / "baselines" / "metrics.json"
    if not is_complete(baselines):
        run(["eval.py", *test, "method=[ego,icpflow]", f"out_dir={baselines.parent}"])
    teacher, ego = dynamic_epe(baselines, "icpflow"), dynamic_epe(baselines, "ego")

    rows = []
    for size in sizes:
        labels = out / "labels" / f"train{size}"
        if not (labels / "index.json").is_file():
            run(
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
            run_dir, scores = out / "runs" / name, out / "eval" / name / "metrics.json"
            timing = run_dir / "train_seconds.txt"
            if not timing.is_file():
                seconds = run(
                    [
                        "train.py",
                        f"experiment={args.experiment}",
                        f"data.train={labels}",
                        f"data.val={val}",
                        f"trainer.max_steps={args.steps}",
                        f"out_dir={run_dir}",
                        f"loss.name={SUPERVISION[supervision]}",
                        "export.formats=[onnx]",
                        "+trainer.enable_progress_bar=false",
                    ]
                )
                write_text_atomic(timing, f"{seconds:.1f}\n")
            if not is_complete(scores):
                run(
                    [
                        "eval.py",
                        *test,
                        "method=[student]",
                        f"checkpoint={run_dir / 'export'}",
                        f"out_dir={scores.parent}",
                    ]
                )
            epe, threeway = dynamic_epe(scores, "student")
            rows.append(
                {
                    "pairs": size,
                    "supervision": supervision,
                    "dynamic_fg_epe": epe,
                    "threeway": threeway,
                    "train_seconds": float(timing.read_text()),
                }
            )

    print(
        f"\nStudent on the synthetic test split ({args.test_sequences * 4} pairs), {args.steps} steps of "
        f"experiment={args.experiment}; teacher {teacher[0]:.4f} m, ego-only {ego[0]:.4f} m dynamic-fg EPE"
    )
    print("| pairs | supervision | dynamic fg EPE (m) | x teacher | Threeway EPE (m) | training (s) |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        print(
            f"| {row['pairs']} | {row['supervision']} | {row['dynamic_fg_epe']:.4f} | "
            f"{row['dynamic_fg_epe'] / teacher[0]:.2f} | {row['threeway']:.4f} | {row['train_seconds']:.0f} |"
        )
    write_text_atomic(
        out / "scaling.json",
        json.dumps(
            {"rows": rows, "teacher": teacher, "ego": ego, "steps": args.steps, "experiment": args.experiment}, indent=2
        ),
    )
    plot(rows, teacher[0], ego[0], out / "scaling.png", args.steps)


def plot(rows: list[dict], teacher: float, ego: float, path: Path, steps: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(6, 4))
    for supervision, style in (("pseudo", "o-"), ("gt", "s--")):
        points = [(r["pairs"], r["dynamic_fg_epe"]) for r in rows if r["supervision"] == supervision]
        if points:
            axis.plot(
                *zip(*points), style, label=f"student, {'pseudo-labels' if supervision == 'pseudo' else 'ground truth'}"
            )
    axis.axhline(teacher, color="green", linestyle=":", label="teacher (ICP-Flow)")
    axis.axhline(ego, color="grey", linestyle=":", label="ego-only flow")
    axis.set_xscale("log", base=2)
    axis.set_xlabel("labelled training pairs")
    axis.set_ylabel("dynamic foreground EPE (m), test split")
    axis.set_title(f"Student data scaling ({steps} steps each)")
    axis.legend()
    figure.tight_layout()
    with atomic_path(path) as tmp:
        figure.savefig(tmp, dpi=120, format="png")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
