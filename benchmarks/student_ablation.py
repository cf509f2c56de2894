"""Recipe ablations of the student over several seeds: each variant (a set of train.py overrides) is trained with
every seed on the same shards, and scored by eval.py on a held-out split (the 64 test pairs by default).

    .venv/bin/python -m benchmarks.student_ablation --train <shards> --val <shards> [--steps 200] [--seeds 0,1,2]
        [--variant NAME=OVERRIDE[,OVERRIDE...] ...] [--experiment synthetic_quick] [--score-split test]
        [--score-sequences 16] [--out outputs/ablation]

Default variants (issue 19): ``base`` (the experiment as it is: ZeroFlow's linear head, all points, uniform loss
weighting, no weight averaging), ``ema`` (callbacks=ema: validation, checkpoints and export use an exponential
moving average of the weights), ``gru`` (model.decoder=gru, DeFlow's point decoder), ``subsample``
(data.train_points=16384, an inexact speed-up), ``buckets`` (loss.weighting=buckets, the speed-bucket loss the
recipes had before the study). Runs go seed by seed (every variant with seed 0 first), so a cut-short study still
compares every variant on the same seeds.
A variant's overrides are split at the commas outside brackets (``corr=model.correlation_levels=[1,2]``); its own
``trainer.max_steps`` replaces ``--steps`` (a slower variant at equal CPU minutes).
Prints, per variant, the dynamic-foreground, static foreground and static background EPE
and Threeway EPE (mean and standard deviation over seeds), the difference of the mean dynamic EPE to ``base`` with
the larger of the two spreads beside it, each seed's dynamic EPE and the mean training time; runs whose scores
exist are not repeated.
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

from benchmarks.common import ROOT, split_overrides
from benchmarks.training_runs import CATEGORIES, trained_and_scored

DEFAULT_VARIANTS = [
    "base=",
    "ema=callbacks=ema",
    "gru=model.decoder=gru",
    "subsample=data.train_points=16384",
    "buckets=loss.weighting=buckets",
]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", type=Path, required=True, help="training shards (a label.py out_dir)")
    parser.add_argument("--val", type=Path, required=True, help="validation shards (checkpoint selection)")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--variant", action="append", help="NAME=OVERRIDE[,OVERRIDE...] (repeatable)")
    parser.add_argument("--experiment", default="synthetic_quick")
    parser.add_argument("--score-split", default="test")
    parser.add_argument("--score-sequences", type=int, default=16, help="sequences of the scored split")
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "ablation")
    args = parser.parse_args()
    variants = {}
    for item in args.variant or DEFAULT_VARIANTS:
        name, _, overrides = item.partition("=")
        variants[name] = split_overrides(overrides)
    seeds = [int(s) for s in args.seeds.split(",")]
    results = {name: [] for name in variants}
    for seed in seeds:
        for name, overrides in variants.items():
            # a variant's own trainer.max_steps (equal CPU minutes for a slower step) replaces --steps
            own_steps = any(o.startswith("trainer.max_steps=") for o in overrides)
            steps = [] if own_steps else [f"trainer.max_steps={args.steps}"]
            train = [
                f"experiment={args.experiment}",
                f"data.train={args.train.resolve()}",
                f"data.val={args.val.resolve()}",
                *steps,
                f"seed={seed}",
                *overrides,
            ]
            test = [f"split={args.score_split}", f"dataset.reader.num_sequences={args.score_sequences}", "bev=0"]
            run_dir = args.out.resolve() / f"{name}_seed{seed}"
            row = trained_and_scored(run_dir, run_dir / "score" / "metrics.json", train, test)
            results[name].append(row)
    print(
        f"\n{args.experiment}, {args.steps} steps, seeds {seeds}; scored on {args.score_split} "
        f"({args.score_sequences} sequences); EPE (m), mean +- std over seeds"
    )
    print(
        "| variant | overrides | dynamic fg | static fg | static bg | Threeway | dynamic fg - base (larger std) "
        "| dynamic fg per seed | training (s) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    base = results.get("base")

    def spread(values):
        return statistics.stdev(values) if len(values) > 1 else 0.0

    for name, rows in results.items():
        cells = []
        for category in (*CATEGORIES, "threeway"):
            values = [row[category] for row in rows]
            cells.append(f"{statistics.mean(values):.4f} +- {spread(values):.4f}")
        dynamic = [row["dynamic_fg"] for row in rows]
        if base is not None and name != "base":
            reference = [row["dynamic_fg"] for row in base]
            worst = max(spread(dynamic), spread(reference))
            cells.append(f"{statistics.mean(dynamic) - statistics.mean(reference):+.4f} ({worst:.4f})")
        else:
            cells.append("-")
        per_seed = ", ".join(f"{value:.3f}" for value in dynamic)
        seconds = statistics.mean(row["seconds"] for row in rows)
        print(f"| {name} | {' '.join(variants[name]) or '-'} | {' | '.join(cells)} | {per_seed} | {seconds:.0f} |")


if __name__ == "__main__":
    main()
