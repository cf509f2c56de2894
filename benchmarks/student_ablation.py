"""Recipe ablations of the student over several seeds: each variant (a set of train.py overrides) is trained with
every seed on the same shards, and scored by eval.py on a held-out split (val by default: decisions are made on
val, reported numbers on test).

    .venv/bin/python benchmarks/student_ablation.py --train <shards> --val <shards> [--steps 200] [--seeds 0,1,2]
        [--variant NAME=OVERRIDE[,OVERRIDE...] ...] [--experiment synthetic_quick] [--score-split val]
        [--score-sequences 16] [--out outputs/ablation]

Default variants: ``base`` (the experiment as it is), ``uniform`` (loss.weighting=uniform), ``speed``
(loss.weighting=speed), ``groupnorm`` (model.norm=group). Prints, per variant, the dynamic-foreground, static
foreground and static background EPE (mean and standard deviation over seeds) and each seed's dynamic EPE; runs
whose scores exist are not repeated.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
from pathlib import Path

from icpflow.evaluation import is_complete, method_summary, read_metrics

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_VARIANTS = [
    "base=",
    "uniform=loss.weighting=uniform",
    "speed=loss.weighting=speed",
    "groupnorm=model.norm=group",
]
CATEGORIES = ("dynamic_fg", "static_fg", "static_bg")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", type=Path, required=True, help="training shards (a label.py out_dir)")
    parser.add_argument("--val", type=Path, required=True, help="validation shards (checkpoint selection)")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--variant", action="append", help="NAME=OVERRIDE[,OVERRIDE...] (repeatable)")
    parser.add_argument("--experiment", default="synthetic_quick")
    parser.add_argument("--score-split", default="val")
    parser.add_argument("--score-sequences", type=int, default=16, help="sequences of the scored split")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "ablation")
    args = parser.parse_args()
    variants = {}
    for item in args.variant or DEFAULT_VARIANTS:
        name, _, overrides = item.partition("=")
        variants[name] = [o for o in overrides.split(",") if o]
    seeds = [int(s) for s in args.seeds.split(",")]
    results = {}
    for name, overrides in variants.items():
        for seed in seeds:
            run_dir = args.out.resolve() / f"{name}_seed{seed}"
            scores = run_dir / "score" / "metrics.json"
            if not is_complete(scores):
                call(
                    [
                        "train.py",
                        f"experiment={args.experiment}",
                        f"data.train={args.train.resolve()}",
                        f"data.val={args.val.resolve()}",
                        f"trainer.max_steps={args.steps}",
                        f"seed={seed}",
                        f"out_dir={run_dir}",
                        "export.formats=[onnx]",
                        "+trainer.enable_progress_bar=false",
                        *overrides,
                    ]
                )
                call(
                    [
                        "eval.py",
                        f"split={args.score_split}",
                        f"dataset.reader.num_sequences={args.score_sequences}",
                        "method=[student]",
                        f"checkpoint={run_dir / 'export'}",
                        f"out_dir={scores.parent}",
                        "bev=0",
                    ]
                )
            table = method_summary(read_metrics(scores), "student")["paper"]["point_weighted"]
            results.setdefault(name, []).append({c: table[c]["EPE"] for c in CATEGORIES})
    print(
        f"\n{args.experiment}, {args.steps} steps, seeds {seeds}; scored on {args.score_split} "
        f"({args.score_sequences} sequences); EPE (m), mean +- std over seeds"
    )
    print("| variant | overrides | dynamic fg | static fg | static bg | dynamic fg per seed |")
    print("|---|---|---|---|---|---|")
    for name, rows in results.items():
        cells = []
        for category in CATEGORIES:
            values = [row[category] for row in rows]
            spread = statistics.stdev(values) if len(values) > 1 else 0.0
            cells.append(f"{statistics.mean(values):.4f} +- {spread:.4f}")
        per_seed = ", ".join(f"{row['dynamic_fg']:.3f}" for row in rows)
        print(f"| {name} | {' '.join(variants[name]) or '-'} | {' | '.join(cells)} | {per_seed} |")


def call(arguments: list[str]) -> None:
    print("$ python " + " ".join(arguments), flush=True)
    subprocess.run([sys.executable, *arguments], cwd=ROOT, check=True, stdout=subprocess.DEVNULL)


if __name__ == "__main__":
    main()
