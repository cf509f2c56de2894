"""Training losses on flat batches: EPE against a target flow (the teacher's pseudo-labels, or ground truth in
comparison runs) with a choice of point weighting.

All flows are ego-compensated (residual) flows (P, 3) in metres per frame gap; ``batch`` (P,) int64 gives each
point's sample; ``valid`` (P,) bool marks the points that count (e.g. inside the grid); ``dt`` seconds, a number or
(P,) per point. Weightings (``loss.weighting``):

- ``uniform``: the mean EPE of each sample's points;
- ``speed``: ZeroFlow's importance weight ``max(0.1, min(1, 1.8 v - 0.8))`` of the target speed v (m/s);
- ``buckets``: the points of a sample are split by target speed at ``bucket_edges`` (m/s); the loss is the sum
  over the non-empty buckets of their mean EPE. Static points keep the weight they have in ``uniform`` (the slowest
  bucket's mean), and the few moving points get buckets of their own instead of drowning in the static majority.

Every loss is a per-sample value averaged over the samples that have valid points.

``object_loss`` (``loss.object_weight`` > 0 adds it, times that weight): per sample, the mean over the teacher's
clusters (``cluster`` (P,) int, -1 = none; the shards hold them) of the EPE between the cluster's mean predicted and
mean target flow. Every object counts alike whatever its point count, and its bias (a whole object moved too little)
is what it measures; the per-point loss lets the static majority drown a small, slow object's few points.
"""

from __future__ import annotations

import torch

from fastflow3d.network.scatter import scatter_sum

WEIGHTINGS = ("uniform", "speed", "buckets")


def speed_weight(target: torch.Tensor, dt: float | torch.Tensor = 0.1) -> torch.Tensor:
    """ZeroFlow's importance weight ``max(0.1, min(1, 1.8 v - 0.8))``, v = target speed in m/s; (P,)."""
    speed = torch.linalg.vector_norm(target, dim=1) / dt
    return (1.8 * speed - 0.8).clamp(min=0.1, max=1.0)


def speed_buckets(target: torch.Tensor, dt: float | torch.Tensor, edges) -> torch.Tensor:
    """(P,) int64 bucket of each point's target speed (m/s): 0 below ``edges[0]``, ..., ``len(edges)`` above."""
    speed = torch.linalg.vector_norm(target, dim=1) / dt
    bounds = torch.as_tensor(list(edges), dtype=speed.dtype, device=speed.device)
    return torch.bucketize(speed, bounds, right=True)


def grouped_mean_sum(
    error: torch.Tensor,
    group: torch.Tensor,
    groups_per_sample: int,
    batch: torch.Tensor,
    valid: torch.Tensor,
    batch_size: int,
) -> torch.Tensor:
    """Mean over samples (with valid points) of the sum over each sample's non-empty groups of the mean ``error``
    (P,) of the group's valid points; ``group`` (P,) int64 in ``[0, groups_per_sample)``."""
    mask = valid.to(error.dtype)
    slots = batch * groups_per_sample + group
    sums = scatter_sum(torch.stack([error * mask, mask], dim=1), slots, batch_size * groups_per_sample)
    sums = sums.reshape(batch_size, groups_per_sample, 2)
    means = sums[..., 0] / sums[..., 1].clamp(min=1.0)
    has_points = sums[..., 1].sum(dim=1) > 0
    return means.sum(dim=1).sum() / has_points.sum().clamp(min=1)


def object_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    cluster: torch.Tensor,
    batch: torch.Tensor,
    valid: torch.Tensor,
    batch_size: int,
) -> torch.Tensor:
    """The module docstring's object term: the mean over samples with clustered valid points of the mean over their
    clusters of ``|mean pred - mean target|``; 0 where no sample has one."""
    keep = valid & (cluster >= 0)
    if not bool(keep.any()):
        return pred.new_zeros(()).float()
    key = batch[keep] * (int(cluster[keep].max()) + 1) + cluster[keep].long()
    groups, slot = torch.unique(key, return_inverse=True)
    values = torch.cat([pred[keep].float(), target[keep].float(), torch.ones_like(pred[keep, :1]).float()], dim=1)
    sums = scatter_sum(values, slot, len(groups))
    error = torch.linalg.vector_norm((sums[:, :3] - sums[:, 3:6]) / sums[:, 6:], dim=1)
    sample = groups // (int(cluster[keep].max()) + 1)
    per_sample = scatter_sum(torch.stack([error, torch.ones_like(error)], dim=1), sample, batch_size)
    present = per_sample[:, 1] > 0
    return (per_sample[present, 0] / per_sample[present, 1]).mean()


def flow_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    batch: torch.Tensor,
    valid: torch.Tensor,
    batch_size: int,
    weighting: str = "uniform",
    dt: float | torch.Tensor = 0.1,
    bucket_edges=(0.4, 1.0),
    point_weight: torch.Tensor | None = None,
) -> torch.Tensor:
    """EPE of ``pred`` against ``target`` with the module docstring's ``weighting``; ``point_weight`` (P,) (e.g. the
    teacher's confidence, or a background weight) multiplies each point's error."""
    if weighting not in WEIGHTINGS:
        raise ValueError(f"loss.weighting must be one of {', '.join(WEIGHTINGS)}, got {weighting!r}")
    error = torch.linalg.vector_norm(pred - target, dim=1)
    if point_weight is not None:
        error = error * point_weight
    if weighting == "speed":
        error = error * speed_weight(target, dt)
    if weighting == "buckets":
        group = speed_buckets(target, dt, bucket_edges)
        return grouped_mean_sum(error, group, len(bucket_edges) + 1, batch, valid, batch_size)
    return grouped_mean_sum(error, torch.zeros_like(batch), 1, batch, valid, batch_size)
