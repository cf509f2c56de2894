"""Learning-rate schedules counted in optimiser steps, for ``conf/scheduler/*.yaml`` (Hydra ``_partial_`` targets).

Each takes the optimiser and ``total_steps`` (filled in by ``fastflow3d.training.student_module`` from the Trainer's
``estimated_stepping_batches``, so a schedule keeps its shape whatever the dataset size) and returns a
``torch.optim.lr_scheduler.LambdaLR`` stepped once per optimiser step. Factors multiply each group's base lr.
"""

from __future__ import annotations

import math

from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR


def _warmup(step: int, warmup_steps: int) -> float:
    """Linear warm-up factor from 1 / (warmup_steps + 1) to 1 over the first ``warmup_steps`` steps."""
    return min(1.0, (step + 1) / (warmup_steps + 1)) if warmup_steps > 0 else 1.0


def _warmup_steps(total_steps: int, warmup_steps: int) -> int:
    """The warm-up length used: ``warmup_steps``, at most half of ``total_steps`` (so a short trial run still
    decays)."""
    if total_steps < 1:
        raise ValueError(f"scheduler: total_steps must be >= 1, got {total_steps}")
    if warmup_steps < 0:
        raise ValueError(f"scheduler: warmup_steps must be >= 0, got {warmup_steps}")
    return min(int(warmup_steps), total_steps // 2)


def warmup_cosine(
    optimizer: Optimizer, total_steps: int, warmup_steps: int = 100, final_factor: float = 0.01
) -> LambdaLR:
    """Linear warm-up over ``warmup_steps``, then a cosine decay from the base lr to ``final_factor`` x base lr at
    ``total_steps``."""
    warmup_steps = _warmup_steps(total_steps, warmup_steps)

    def factor(step: int) -> float:
        if step < warmup_steps:
            return _warmup(step, warmup_steps)
        progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
        return final_factor + (1.0 - final_factor) * 0.5 * (1.0 + math.cos(math.pi * progress))

    return LambdaLR(optimizer, factor)


def warmup_multistep(
    optimizer: Optimizer,
    total_steps: int,
    warmup_steps: int = 0,
    milestones: tuple[float, ...] = (0.5,),
    gamma: float = 0.1,
) -> LambdaLR:
    """Linear warm-up, then the lr times ``gamma`` at each milestone, given as a fraction of ``total_steps``
    (0.5 = half way: the paper's "x0.1 after 25 of 50 epochs")."""
    warmup_steps = _warmup_steps(total_steps, warmup_steps)
    if any(not 0.0 < m < 1.0 for m in milestones):
        raise ValueError(f"scheduler: milestones are fractions of total_steps in (0, 1), got {list(milestones)}")
    steps = sorted(round(m * total_steps) for m in milestones)

    def factor(step: int) -> float:
        return _warmup(step, warmup_steps) * gamma ** sum(step >= s for s in steps)

    return LambdaLR(optimizer, factor)
