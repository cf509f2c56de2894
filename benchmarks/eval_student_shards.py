"""A trained student against its teacher on labelled shards that carry ground truth (paper metrics, point-weighted).

Usage: python benchmarks/eval_student_shards.py CHECKPOINT [--shards outputs/labels/synthetic/val] [--crop 32]
Rows: the teacher (the shards' pseudo-labels), the student (CHECKPOINT, full flow = residual + ego flow; points
outside its grid get the ego flow) and the ego-flow baseline, all scored against the shards' ground truth.
"""

import argparse
import statistics
import time

import torch

from fastflow3d.checkpoint import load_student
from fastflow3d.data import StudentDataset, collate
from icpflow import metrics
from icpflow.geometry import ego_flow, residual_to_full


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--shards", default="outputs/labels/synthetic/val")
    parser.add_argument("--crop", type=float, default=32.0)
    args = parser.parse_args()
    model, _ = load_student(args.checkpoint)
    dataset = StudentDataset(args.shards)
    scores = {name: metrics.MetricAccumulator() for name in ("teacher", "student", "ego flow")}
    seconds = []
    for index in range(len(dataset)):
        sample = dataset[index]
        if "gt" not in sample:
            raise SystemExit(f"{args.shards}: sample {sample['sample_id']} has no ground truth")
        batch = collate([sample])
        start = time.perf_counter()
        with torch.no_grad():
            residual, _ = model(batch["pc0_compensated"], batch["batch0"], batch["pc1"], batch["batch1"], 1)
        seconds.append(time.perf_counter() - start)
        pc0, ego = sample["pc0"].numpy(), sample["ego1_from_ego0"].numpy()
        flows = {"teacher": residual_to_full(sample["pseudo"].numpy(), pc0, ego),
                 "student": residual_to_full(residual.numpy(), pc0, ego), "ego flow": ego_flow(pc0, ego)}
        gt = residual_to_full(sample["gt"].numpy(), pc0, ego)
        for name, flow in flows.items():
            scores[name].add(metrics.pair_stats(pc0, flow, gt, ego, sample["gt_classes"].numpy(),
                                                ground=sample["ground0"].numpy(), flow_valid=sample["gt_valid"].numpy(),
                                                dt=float(sample["dt"]), crop=args.crop))
    print(f"{len(dataset)} pairs of {args.shards}, crop {args.crop} m, ground excluded, point-weighted; "
          f"student forward {statistics.median(seconds) * 1e3:.0f} ms per pair (median, this CPU)")
    print(metrics.format_table({name: acc.table()["point_weighted"] for name, acc in scores.items()}))


if __name__ == "__main__":
    main()
