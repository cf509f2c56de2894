"""Training losses on flat batches: ZeroFlow distillation on pseudo-labels and a supervised loss on ground truth.

All flows are ego-compensated (residual) flows (P, 3) in metres per frame gap; ``batch`` (P,) int64 gives each
point's sample; ``valid`` (P,) bool marks the points that count (e.g. inside the grid).
"""

import torch

from fastflow3d.scatter import scatter_sum


def speed_weight(pseudo: torch.Tensor, dt: float | torch.Tensor = 0.1) -> torch.Tensor:
    """ZeroFlow's importance weight ``max(0.1, min(1, 1.8 v - 0.8))``, v = pseudo-label speed in m/s; (P,).

    ``dt`` in seconds: a number, or (P,) per point (a batch mixing frame rates)."""
    speed = torch.linalg.vector_norm(pseudo, dim=1) / dt
    return (1.8 * speed - 0.8).clamp(min=0.1, max=1.0)


def weighted_epe(pred: torch.Tensor, target: torch.Tensor, weight: torch.Tensor, batch: torch.Tensor,
                 valid: torch.Tensor, batch_size: int) -> torch.Tensor:
    """Per sample mean over valid points of ``weight * ||pred - target||_2``, averaged over samples with points."""
    error = weight * torch.linalg.vector_norm(pred - target, dim=1)
    mask = valid.to(error.dtype)
    sums = scatter_sum(torch.stack([error * mask, mask], dim=1), batch, batch_size)
    has_points = sums[:, 1] > 0
    per_sample = sums[:, 0] / sums[:, 1].clamp(min=1.0)
    return (per_sample * has_points).sum() / has_points.sum().clamp(min=1)


def distillation_loss(pred: torch.Tensor, pseudo: torch.Tensor, batch: torch.Tensor, valid: torch.Tensor,
                      batch_size: int, use_speed_weight: bool = False, dt: float | torch.Tensor = 0.1,
                      confidence: torch.Tensor | None = None) -> torch.Tensor:
    """ZeroFlow loss on pseudo-labels; optional speed weight (``dt`` in s) and per-point confidence (P,) weight."""
    weight = speed_weight(pseudo, dt) if use_speed_weight else torch.ones_like(pred[:, 0])
    if confidence is not None:
        weight = weight * confidence
    return weighted_epe(pred, pseudo, weight, batch, valid, batch_size)


def supervised_loss(pred: torch.Tensor, gt: torch.Tensor, foreground: torch.Tensor, batch: torch.Tensor,
                    valid: torch.Tensor, batch_size: int, background_weight: float = 0.1) -> torch.Tensor:
    """Loss on ground-truth residual flow; foreground (P,) bool points weigh 1, background ``background_weight``."""
    weight = torch.where(foreground, torch.ones_like(pred[:, 0]), torch.full_like(pred[:, 0], background_weight))
    return weighted_epe(pred, gt, weight, batch, valid, batch_size)
