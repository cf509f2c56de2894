"""Where one training step of the student spends its time, and how empty its grid is: the step (forward, loss,
backward, Adam) on real batches of a label folder, on one thread, under ``torch.profiler``.

    .venv/bin/python -m benchmarks.profile_training_step --train <label.py out_dir> [--runs 5] [OVERRIDE ...]

``OVERRIDE``s are train.py's (default ``experiment=synthetic_cpu``). Prints the median step (process time, so the
figure holds on a shared machine), the profiler's self time per operator family (forward and backward together;
shares are what to read: the profiler's own overhead inflates the seconds), and, per UNet level, the share of
pillar cells that hold a point of either scan (the network's input after its ground removal and crop) beside the
share of the convolutions' time spent at that level. From them, the time the convolutions would take if they ran at
the occupied cells only (a sparse layout doing the same work per cell: an upper bound on what it saves, since sparse
convolutions on a CPU do less per second than dense ones, and submanifold convolutions are a different network).
"""

from __future__ import annotations

import argparse
import collections
import statistics
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from benchmarks.common import compose

#: operator families, first match of a substring of the profiler's operator name wins
FAMILIES = (
    ("convolution", ("conv",)),
    ("normalisation", ("batch_norm", "group_norm")),
    ("activation", ("gelu",)),
    ("upsampling", ("upsample", "interpolate")),
    ("scatter / gather", ("index", "scatter", "gather", "unique", "segment", "bincount", "embedding")),
    ("concatenation / copies", ("cat", "copy_", "clone", "contiguous", "to_copy", "pad")),
    ("linear layers", ("linear", "addmm", "mm", "matmul", "bmm")),
    ("optimiser", ("_foreach", "adam", "lerp", "addcdiv", "addcmul", "sqrt")),
)


def family(name: str) -> str:
    low = name.lower()
    return next((label for label, keys in FAMILIES if any(key in low for key in keys)), "other (elementwise, loss)")


def occupancy(points: torch.Tensor, index: torch.Tensor, grid, batch_size: int, levels: int) -> list[float]:
    """Per UNet level 0..levels-1 (a cell of level k is 2^k pillars wide): the share of the batch's cells holding a
    point of ``points`` (P, 3) (``index`` (P,): each point's sample)."""
    ix = torch.floor((points[:, 0] - grid.x_range[0]) / grid.cell).long()
    iy = torch.floor((points[:, 1] - grid.y_range[0]) / grid.cell).long()
    inside = (ix >= 0) & (ix < grid.nx) & (iy >= 0) & (iy < grid.ny)
    mask = torch.zeros(batch_size, 1, grid.nx, grid.ny)
    mask[index[inside], 0, ix[inside], iy[inside]] = 1.0
    return [float((torch.nn.functional.max_pool2d(mask, 2**k) if k else mask).mean()) for k in range(levels)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", type=Path, required=True, help="a label.py out_dir (its batches are profiled)")
    parser.add_argument("--runs", type=int, default=5, help="steps profiled after one warm-up step")
    parser.add_argument("overrides", nargs="*", default=["experiment=synthetic_cpu"])
    args = parser.parse_args()
    torch.set_num_threads(1)
    from fastflow3d.training import data as data_module
    from fastflow3d.training.precision import BF16, choose_precision
    from fastflow3d.training.trainer import build_module, training_contract

    cfg = compose("train", [f"data.train={args.train.resolve()}", f"data.val={args.train.resolve()}", *args.overrides])
    plain = OmegaConf.to_container(cfg, resolve=True)
    torch.manual_seed(0)
    module = build_module(cfg, training_contract(cfg), plain).train()
    datamodule = data_module.ShardDataModule.from_config(plain["data"], module.contract)
    datamodule.setup("fit")
    dataset, size = datamodule.train_set, plain["data"]["batch_size"]
    optimiser = torch.optim.Adam(module.parameters(), lr=1e-4)
    precision, line, _ = choose_precision(plain["trainer"]["precision"], "cpu")
    print(line)
    bf16 = precision in BF16
    network = module.model
    levels = len(network.unet.encoder) + 1
    families, by_side, steps = collections.Counter(), collections.Counter(), []
    occupied = collections.defaultdict(list)
    for run in range(args.runs + 1):
        batch = data_module.collate([dataset[(run * size + i) % len(dataset)] for i in range(size)])
        activities = [torch.profiler.ProfilerActivity.CPU]
        with torch.profiler.profile(activities=activities, record_shapes=True) as profile:
            tic = time.process_time()
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                pred, valid = module(batch)
                loss = module.loss(pred, valid, batch)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
            elapsed = time.process_time() - tic
        if run == 0:
            continue  # warm-up
        steps.append(elapsed)
        for event in profile.key_averages():
            families[family(event.key)] += event.self_cpu_time_total / 1e6 / args.runs
        for event in profile.key_averages(group_by_input_shape=True):
            sides = [shape[-1] for shape in event.input_shapes if len(shape) == 4 and shape[-1] > 3]
            if family(event.key) == "convolution" and sides:
                by_side[max(sides)] += event.self_cpu_time_total / 1e6 / args.runs
        for cloud, index in (("pc0", "batch0"), ("pc1", "batch1")):
            for level, share in enumerate(occupancy(batch[cloud], batch[index], network.grid, size, levels)):
                occupied[level].append(share)
    total, convolutions = sum(families.values()), sum(by_side.values())
    print(f"one step, batch {size}, 1 thread, bf16 {bf16}: {statistics.median(steps):.3f} s (median process time)")
    print("\n| operator family | profiled s per step | share |\n|---|---|---|")
    for name, seconds in families.most_common():
        print(f"| {name} | {seconds:.3f} | {seconds / total:.1%} |")
    print("\n| UNet level | cell (m) | grid | occupied cells | share of the convolutions' time |")
    print("|---|---|---|---|---|")
    sparse = 0.0
    for level in range(levels):
        side, share = network.grid.nx // 2**level, by_side.get(network.grid.nx // 2**level, 0.0) / convolutions
        cells = statistics.mean(occupied[level])
        sparse += share * cells
        print(f"| {level} | {network.grid.cell * 2**level:g} | {side} x {side} | {cells:.1%} | {share:.1%} |")
    step = 1 - families["convolution"] / total * (1 - sparse)
    print(
        f"\nconvolutions at the occupied cells only: {sparse:.1%} of their time; the step at {step:.0%} of today's "
        "(every other operator as it is)"
    )


if __name__ == "__main__":
    main()
