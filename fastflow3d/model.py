"""FastFlow3D (as ZeroFlow implements it): pillar embedder, two-scan UNet and a per-point flow head.

Input convention: ``pc0`` is the scan at t already moved into the ego frame of t + dt (``ego1_from_ego0``
applied, see ``compensate``) and ``pc1`` is the scan at t + dt as is. The network predicts the ego-compensated
(residual) flow of every pc0 point inside the grid (0 outside, with a validity mask); the full flow in the
project convention is ``residual + ego_flow(pc0, ego1_from_ego0)`` (``icpflow.geometry.residual_to_full``).
Batches are flat point lists with a sample index per point (see ``fastflow3d.voxelize``).
"""

import numpy as np
import torch
from torch import nn

from fastflow3d.scatter import from_pseudo_image, scatter_mean, to_pseudo_image
from fastflow3d.voxelize import Grid, voxelize
from icpflow.geometry import transform_points


def compensate(pc0: np.ndarray, ego1_from_ego0: np.ndarray) -> np.ndarray:
    """Model input for pc0: its (N, 3) points moved into the ego frame of t + dt."""
    return transform_points(ego1_from_ego0, pc0)


NORMS = ("batch", "group")


def norm_layer(norm: str, channels: int, embedder: bool = False) -> nn.Module:
    """``batch``: BatchNorm (ZeroFlow's; the embedder's with eps 1e-3, momentum 0.01); ``group``: GroupNorm with
    groups of 8 channels (one group over a point's channels in the embedder), which has no running statistics."""
    if norm == "batch":
        return nn.BatchNorm1d(channels, eps=1e-3, momentum=0.01) if embedder else nn.BatchNorm2d(channels)
    return nn.GroupNorm(1 if embedder else max(1, channels // 8), channels)


class ConvNormAct(nn.Sequential):
    """Conv2d (with bias) + norm (``norm_layer``) + GELU."""

    def __init__(self, c_in: int, c_out: int, stride: int = 1, norm: str = "batch"):
        super().__init__(nn.Conv2d(c_in, c_out, 3, stride, 1), norm_layer(norm, c_out), nn.GELU())


def encoder_stage(c_in: int, c_out: int, blocks: int, norm: str = "batch") -> nn.Sequential:
    """One stride-2 conv c_in -> c_out then ``blocks`` convs c_out -> c_out (resolution halves)."""
    return nn.Sequential(
        ConvNormAct(c_in, c_out, 2, norm), *[ConvNormAct(c_out, c_out, 1, norm) for _ in range(blocks)]
    )


class UpsampleSkip(nn.Module):
    """Decoder step: low (skip, h, w) -> 1x1 conv to latent, bilinear x2; high (latent, 2h, 2w) -> 1x1 conv;
    concatenate, 3x3 conv 2 * latent -> out, 3x3 conv out -> out (no norm, no activation)."""

    def __init__(self, skip: int, latent: int, out: int):
        super().__init__()
        self.low = nn.Conv2d(skip, latent, 1)
        self.high = nn.Conv2d(latent, latent, 1)
        self.fuse = nn.Sequential(nn.Conv2d(2 * latent, out, 3, 1, 1), nn.Conv2d(out, out, 3, 1, 1))

    def forward(self, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
        up = nn.functional.interpolate(self.low(low), scale_factor=2.0, mode="bilinear", align_corners=False)
        return self.fuse(torch.cat([up, self.high(high)], dim=1))


class UNet(nn.Module):
    """Shared encoder on both pseudo-images (B, C, H, W); skips concatenate both scans; output (B, 2C, H, W)."""

    def __init__(self, pillar_channels: int, stage_channels, stage_blocks, norm: str = "batch"):
        super().__init__()
        widths = [pillar_channels, *stage_channels]
        self.encoder = nn.ModuleList(
            encoder_stage(c_in, c_out, n, norm) for c_in, c_out, n in zip(widths[:-1], widths[1:], stage_blocks)
        )
        skips = [2 * w for w in widths]  # concatenated widths, finest first
        self.decoder = nn.ModuleList(
            UpsampleSkip(skips[i + 1], skips[i], skips[i]) for i in reversed(range(len(skips) - 1))
        )
        self.final = nn.Conv2d(skips[0], skips[0], 3, 1, 1)

    def forward(self, image0: torch.Tensor, image1: torch.Tensor) -> torch.Tensor:
        levels = [torch.cat([image0, image1], dim=1)]
        for stage in self.encoder:
            image0, image1 = stage(image0), stage(image1)
            levels.append(torch.cat([image0, image1], dim=1))
        x = levels[-1]
        for step, skip in zip(self.decoder, reversed(levels[:-1])):
            x = step(x, skip)
        return self.final(x)


class PillarEmbedder(nn.Module):
    """Per-point Linear(9 -> C, no bias) + norm (BatchNorm1d(eps 1e-3, momentum 0.01), or a per-point GroupNorm)
    + ReLU, mean per pillar."""

    def __init__(self, channels: int, norm: str = "batch"):
        super().__init__()
        self.linear = nn.Linear(9, channels, bias=False)
        self.norm = norm_layer(norm, channels, embedder=True)

    def forward(self, features: torch.Tensor, ids: torch.Tensor, valid: torch.Tensor, num_slots: int):
        """Pillar rows (num_slots, C) from point features (P, 9); batch statistics use in-range points only."""
        h = self.linear(features)
        if self.training and isinstance(self.norm, nn.BatchNorm1d):
            normed = torch.zeros_like(h)
            normed[valid] = self.norm(h[valid])
        else:
            normed = self.norm(h)
        return scatter_mean(torch.relu(normed), ids, num_slots)


class FastFlow3D(nn.Module):
    """FastFlow3D on flat batches. ``forward(pc0, batch0, pc1, batch1, batch_size)`` -> (residual (P0, 3), valid).

    pc0 (P0, 3) ego-compensated, pc1 (P1, 3), batch0/batch1 int64 sample indices in ``[0, batch_size)``.

    Every argument but ``norm`` is required: the settings live in one place, ``conf/model/*.yaml``
    (``fastflow3d.yaml`` is FastFlow3D as ZeroFlow implements it; the others extend it), and a checkpoint carries
    them all (``norm`` defaults to ``batch`` for checkpoints written before it existed).
    """

    def __init__(self, *, x_range, y_range, z_range, cell, pillar_channels, stage_channels, stage_blocks, norm="batch"):
        super().__init__()
        if norm not in NORMS:
            raise ValueError(f"FastFlow3D: norm must be one of {', '.join(NORMS)}, got {norm!r}")
        if len(stage_channels) != len(stage_blocks):
            raise ValueError(f"FastFlow3D: {len(stage_channels)} stage_channels but {len(stage_blocks)} stage_blocks")
        self.grid = Grid(tuple(x_range), tuple(y_range), tuple(z_range), float(cell))
        factor = 2 ** len(stage_channels)
        if self.grid.nx % factor or self.grid.ny % factor:
            raise ValueError(f"FastFlow3D: grid {self.grid.nx}x{self.grid.ny} not divisible by {factor}")
        self.embedder = PillarEmbedder(pillar_channels, norm)
        self.unet = UNet(pillar_channels, tuple(stage_channels), tuple(stage_blocks), norm)
        self.head = nn.Sequential(nn.Linear(4 * pillar_channels + 3, 32), nn.GELU(), nn.Linear(32, 3))

    def embed(self, points: torch.Tensor, batch: torch.Tensor, batch_size: int):
        """Pseudo-image (B, C, nx, ny), per-point features (P, 9), pillar ids and in-range mask of one scan."""
        features, ids, valid = voxelize(points, batch, self.grid, batch_size)
        rows = self.embedder(features, ids, valid, batch_size * self.grid.nx * self.grid.ny + 1)
        return to_pseudo_image(rows, batch_size, self.grid.nx, self.grid.ny), features, ids, valid

    def forward(
        self, pc0: torch.Tensor, batch0: torch.Tensor, pc1: torch.Tensor, batch1: torch.Tensor, batch_size: int = 1
    ):
        image0, features0, ids0, valid0 = self.embed(pc0, batch0, batch_size)
        image1, _, _, _ = self.embed(pc1, batch1, batch_size)
        decoded = self.unet(image0, image1)
        per_point = torch.cat(
            [
                from_pseudo_image(image0, ids0),
                from_pseudo_image(image1, ids0),
                from_pseudo_image(decoded, ids0),
                features0[:, 6:9],
            ],
            dim=1,
        )
        residual = self.head(per_point)
        return torch.where(valid0[:, None], residual, torch.zeros_like(residual)), valid0
