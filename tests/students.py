"""Tiny trained FastFlow3D checkpoints for the export, inference and evaluation tests."""

from __future__ import annotations

import numpy as np
import torch

from fastflow3d.loss import flow_loss
from fastflow3d.model import FastFlow3D, compensate


def tiny_model(half_width: float, cell: float) -> dict:
    """The config (``conf/model`` form) of a tiny FastFlow3D over ``[-half_width, half_width]^2`` m with ``cell``
    m pillars: 8 pillar channels, encoders of 8 / 16 / 32 channels with one extra conv each."""
    return {
        "_target_": "fastflow3d.model.FastFlow3D",
        "x_range": [-half_width, half_width],
        "y_range": [-half_width, half_width],
        "z_range": [-3.0, 3.0],
        "cell": cell,
        "pillar_channels": 8,
        "stage_channels": [8, 16, 32],
        "stage_blocks": [1, 1, 1],
    }


def tiny_checkpoint(path, model_cfg: dict, pair, steps: int, keep0=None, keep1=None, cfg: dict | None = None):
    """Save at ``path`` a training checkpoint (the ``fastflow3d.checkpoint`` contract) of the FastFlow3D of
    ``model_cfg`` after ``steps`` Adam steps towards ``pair``'s true residual flow (on the rows ``keep0`` / ``keep1``
    of its scans, all by default), so that its weights and BatchNorm statistics are not the initial ones.
    ``cfg``: further entries of the saved training config. Returns ``path``."""
    keep0 = np.arange(len(pair.pc0)) if keep0 is None else keep0
    keep1 = np.arange(len(pair.pc1)) if keep1 is None else keep1
    torch.manual_seed(0)
    model = FastFlow3D(**{k: v for k, v in model_cfg.items() if k != "_target_"}).train()
    pc0 = torch.from_numpy(compensate(pair.pc0[keep0], pair.ego1_from_ego0))
    pc1 = torch.from_numpy(pair.pc1[keep1])
    target = torch.from_numpy(pair.residual_flow()[keep0])
    batch0, batch1 = torch.zeros(len(pc0), dtype=torch.int64), torch.zeros(len(pc1), dtype=torch.int64)
    optimiser = torch.optim.Adam(model.parameters(), lr=2e-3)
    for _ in range(steps):
        residual, valid = model(pc0, batch0, pc1, batch1, 1)
        loss = flow_loss(residual, target, batch0, valid, 1)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    torch.save(
        {
            "state_dict": {f"model.{key}": value for key, value in model.state_dict().items()},
            "hyper_parameters": {"cfg": {"model": dict(model_cfg), **(cfg or {})}},
            "epoch": 0,
            "global_step": steps,
        },
        path,
    )
    return path
