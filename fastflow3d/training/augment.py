"""Training augmentation of one shard sample, applied consistently to both scans, the flows and the ego motion.

A random transform ``A(x) = R x + s`` acts on both ego frames alike: R is a yaw rotation about the ego z axis,
optionally composed with the mirror ``y -> -y``, and s = (0, 0, dz) a small height shift. Points map as
``pc0' = A pc0`` and ``pc1' = A pc1``, the ego motion as ``ego1_from_ego0' = A ego1_from_ego0 A^-1`` (still a
proper rigid transform, also after a mirror), and every flow vector (full, residual, ground truth) as ``R v``, so
``pc0' + flow'`` is again the point's position at t + dt in the (transformed) ego frame of t + dt. Point
subsampling then keeps a random fraction of each scan's rows with their per-point values. Works on the numpy
dict a ``icpflow.shards.reader.ShardDataset`` returns (``pc0``, ``pc1``, ``ego1_from_ego0``, ``flow``, ``ground0``,
``ground1``, ``confidence``, ``cluster``, optional ``gt_flow``, ``gt_flow_valid``, ``gt_classes``, ...).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from icpflow.core.geometry import invert, make_transform, transform_points
from icpflow.shards.schema import CLOUD, OPTIONAL, REQUIRED

#: the shard schema's per-point arrays, by the cloud whose rows they follow
PER_POINT = {name: shape for name, (_, shape) in {**REQUIRED, **OPTIONAL}.items() if shape in (None, 3)}
POINT_KEYS = {cloud: tuple(k for k in PER_POINT if CLOUD.get(k, "pc0") == cloud) for cloud in ("pc0", "pc1")}
FLOW_KEYS = ("flow", "gt_flow")


@dataclass(frozen=True)
class Augmentation:
    """``yaw_deg``: rotation uniform in [-yaw_deg, yaw_deg] degrees; ``flip``: mirror y with probability 0.5;
    ``height_shift``: dz uniform in [-height_shift, height_shift] m; ``keep_min``: each scan keeps a uniform
    fraction in [keep_min, 1] of its points (1 = no subsampling)."""

    yaw_deg: float = 20.0
    flip: bool = True
    height_shift: float = 0.1
    keep_min: float = 0.8

    def __post_init__(self):
        if not 0.0 <= self.yaw_deg <= 180.0:
            raise ValueError(f"augment.yaw_deg must lie in [0, 180], got {self.yaw_deg}")
        if self.height_shift < 0.0:
            raise ValueError(f"augment.height_shift must be >= 0, got {self.height_shift}")
        if not 0.0 < self.keep_min <= 1.0:
            raise ValueError(f"augment.keep_min must lie in (0, 1], got {self.keep_min}")

    def draw(self, rng: np.random.Generator) -> np.ndarray:
        """A random (4, 4) float64 transform A (yaw, optional mirror, height shift)."""
        yaw = np.radians(rng.uniform(-self.yaw_deg, self.yaw_deg))
        mirror = np.diag([1.0, -1.0 if self.flip and rng.random() < 0.5 else 1.0, 1.0])
        transform = make_transform(yaw=yaw, translation=(0.0, 0.0, rng.uniform(-self.height_shift, self.height_shift)))
        transform[:3, :3] = transform[:3, :3] @ mirror
        return transform

    def __call__(self, sample: dict, rng: np.random.Generator) -> dict:
        """A new sample dict: ``sample`` moved by a random A (module docstring), then subsampled."""
        return subsample(transform_sample(sample, self.draw(rng)), rng, self.keep_min)


def transform_sample(sample: dict, transform: np.ndarray) -> dict:
    """``sample`` with both scans moved by the (4, 4) ``transform`` A, flows rotated, the ego motion conjugated."""
    rotation = transform.copy()
    rotation[:3, 3] = 0.0  # flows are vectors: they turn but do not shift
    out = dict(sample)
    for key in ("pc0", "pc1"):
        out[key] = transform_points(transform, sample[key])
    for key in FLOW_KEYS:
        if sample.get(key) is not None:
            out[key] = transform_points(rotation, sample[key])
    out["ego1_from_ego0"] = transform @ sample["ego1_from_ego0"] @ invert(transform)
    return out


def subsample(sample: dict, rng: np.random.Generator, keep_min: float) -> dict:
    """Each scan keeps a random fraction in [keep_min, 1] of its rows (sorted; at least one), per-point values
    included."""
    if keep_min >= 1.0:
        return sample
    out = dict(sample)
    for cloud, keys in POINT_KEYS.items():
        count = len(sample[cloud])
        kept = max(1, int(round(count * rng.uniform(keep_min, 1.0))))
        rows = np.sort(rng.choice(count, size=kept, replace=False))
        for key in keys:
            if sample.get(key) is not None:
                out[key] = sample[key][rows]
    return out
