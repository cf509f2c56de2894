"""Time to generate one synthetic pair (world, two scans, ground truth) at 64 and 32 beams; median of runs.

Run from the repository root: ``.venv/bin/python -m benchmarks.bench_synthetic --repeats 5``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from icpflow.datasets.synthetic import Lidar, build_scene, sequence


def one_pair(seed: int, lidar: Lidar):
    """Build the world of ``seed``, cast scans 0 and 1, and return the pair (0, 1) with its ground truth."""
    return sequence(build_scene(seed, frames=2), lidar).pair(0, 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=1_000_000)
    args = parser.parse_args()
    print(f"{'sensor':<28}{'points/scan':>12}{'ms/pair':>10}{'min ms':>9}{'pairs/s':>9}")
    for name, lidar in (("64 beams, 0.2 deg, 75 m", Lidar(beams=64)), ("32 beams, 0.2 deg, 75 m", Lidar(beams=32))):
        one_pair(args.seed, lidar)  # warm-up
        times, points = [], []
        for run in range(args.repeats):
            start = time.perf_counter()
            pair = one_pair(args.seed + run, lidar)
            times.append(time.perf_counter() - start)
            points += [len(pair.pc0), len(pair.pc1)]
        median = float(np.median(times))
        print(f"{name:<28}{int(np.median(points)):>12}{median * 1e3:>10.1f}{min(times) * 1e3:>9.1f}{1 / median:>9.2f}")


if __name__ == "__main__":
    main()
