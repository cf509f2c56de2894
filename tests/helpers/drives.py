"""Synthetic drives for the odometry and stream tests: the pairs of one sequence and its scans in order."""

from __future__ import annotations

import numpy as np

from icpflow.core.frame_pair import FramePair
from icpflow.datasets.synthetic.reader import SyntheticDataset


def synthetic_drive(seed: int, frames: int, beams: int = 32) -> tuple[list[FramePair], list[np.ndarray]]:
    """One test sequence of ``frames`` scans: its ``frames - 1`` consecutive pairs and the scans (pc0 of the first
    pair, then every pair's pc1), each (N, 3) float32 in its own ego frame."""
    data = SyntheticDataset(split="test", num_sequences=1, frames_per_sequence=frames, beams=beams, seed=seed)
    pairs = [data[i] for i in range(len(data))]
    return pairs, [pairs[0].pc0] + [pair.pc1 for pair in pairs]


def corridor(seed: int, shift: float = 0.0) -> np.ndarray:
    """Two parallel walls 6 m apart, 40 m long and 3 m high, as a scan would see them (x forward), moved back by
    ``shift`` m: nothing in them fixes the motion along x."""
    rng = np.random.default_rng(seed)
    walls = [
        np.column_stack([rng.uniform(-20, 20, 15000), np.full(15000, side) + rng.normal(0, 0.01, 15000)])
        for side in (-3.0, 3.0)
    ]
    points = np.concatenate([np.column_stack([w, rng.uniform(0.2, 3.0, len(w))]) for w in walls])
    points[:, 0] -= shift
    return points.astype(np.float32)
