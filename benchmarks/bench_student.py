"""FastFlow3D forward and forward+backward time per sample on this CPU (median of several runs).

Usage: python benchmarks/bench_student.py [--points 80000] [--runs 5] [--batch 1] [--cell 0.2] [--threads N]
Input: two uniform random scans in range (AV2-size after ground removal, about 80k points each).
"""

import argparse
import statistics
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from fastflow3d.checkpoint import build_student
from fastflow3d.loss import distillation_loss

#: the paper's FastFlow3D settings (the one place of the model's settings); --cell changes the pillar size
PAPER_MODEL = Path(__file__).resolve().parents[1] / "conf" / "model" / "fastflow3d.yaml"


def random_scan(points: int, batch: int, seed: int):
    """Flat batch of ``batch`` uniform scans in [-51.2, 51.2]^2 x [-3, 3] with ``points`` points each."""
    gen = torch.Generator().manual_seed(seed)
    scale, low = torch.tensor([102.4, 102.4, 6.0]), torch.tensor([51.2, 51.2, 3.0])
    xyz = torch.rand(points * batch, 3, generator=gen) * scale - low
    return xyz, torch.arange(batch).repeat_interleave(points)


def timed(fn, runs: int) -> list[float]:
    """Wall-clock seconds of ``runs`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return times


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=80_000)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--batch", type=int, default=1)
    parser.add_argument("--cell", type=float, default=0.2)
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model = build_student({**OmegaConf.to_container(OmegaConf.load(PAPER_MODEL)), "cell": args.cell})
    pc0, b0 = random_scan(args.points, args.batch, 0)
    pc1, b1 = random_scan(args.points, args.batch, 1)
    target = torch.randn(len(pc0), 3) * 0.1

    def forward():
        model.eval()
        with torch.no_grad():
            model(pc0, b0, pc1, b1, args.batch)

    def forward_backward():
        model.train()
        model.zero_grad(set_to_none=True)
        pred, valid = model(pc0, b0, pc1, b1, args.batch)
        distillation_loss(pred, target, b0, valid, args.batch).backward()

    params = sum(p.numel() for p in model.parameters())
    print(
        f"FastFlow3D grid {model.grid.nx}x{model.grid.ny}, {params:,} parameters, batch {args.batch}, "
        f"{args.points} points per scan, {args.threads} threads, torch {torch.__version__}"
    )
    print("| step | median s/sample | min s/sample | runs |")
    print("|---|---|---|---|")
    for name, fn in (("forward (eval, no grad)", forward), ("forward + backward (train)", forward_backward)):
        times = [t / args.batch for t in timed(fn, args.runs)]
        print(f"| {name} | {statistics.median(times):.3f} | {min(times):.3f} | {args.runs} |")


if __name__ == "__main__":
    main()
