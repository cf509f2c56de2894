"""FastFlow3D (as ZeroFlow implements it): pillar embedder, two-scan UNet and a per-point flow decoder: ZeroFlow's
Linear-GELU-Linear head (``decoder="linear"``) or a DeFlow-style GRU refinement of each point's feature
(``decoder="gru"``, Zhang et al., ICRA 2024).

Input convention: ``pc0`` is the scan at t already moved into the ego frame of t + dt (``ego1_from_ego0``
applied, see ``compensate``) and ``pc1`` is the scan at t + dt as is. The network predicts the ego-compensated
(residual) flow of every pc0 point inside the grid (0 outside, with a validity mask); the full flow in the
project convention is ``residual + ego_flow(pc0, ego1_from_ego0)`` (``icpflow.core.geometry.residual_to_full``).
Batches are flat point lists with a sample index per point (see ``fastflow3d.network.voxelize``).

Speed (the numbers are those of the plain formulation up to float rounding): pseudo-images are channels_last views
of the pillar rows (no copy, and the convolutions run in channels_last); the decoders' first layer is split into
a per-pillar part, computed once per cell of the pseudo-images, and a per-point part, so the three pillar features
are never gathered per point; the embedder's BatchNorm skips its masked copy when every point is inside the grid
(training batches are cropped to the grid by ``fastflow3d.training.data``).
"""

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from fastflow3d.network.cells import CellSets, conv3x3_at, image_rows, rows_at, with_zero_row
from fastflow3d.network.scatter import scatter_mean, scatter_sum, to_pseudo_image
from fastflow3d.network.voxelize import Grid, voxelize
from icpflow.core.geometry import transform_points


def compensate(pc0: np.ndarray, ego1_from_ego0: np.ndarray) -> np.ndarray:
    """Model input for pc0: its (N, 3) points moved into the ego frame of t + dt."""
    return transform_points(ego1_from_ego0, pc0)


NORMS = ("batch", "group")
DECODERS = ("linear", "gru")


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
        return self.fuse(torch.cat([self.upsampled(low), self.high(high)], dim=1))

    def upsampled(self, low: torch.Tensor) -> torch.Tensor:
        return nn.functional.interpolate(self.low(low), scale_factor=2.0, mode="bilinear", align_corners=False)

    def at_cells(self, low: torch.Tensor, high: torch.Tensor, sets: CellSets, final: nn.Conv2d) -> torch.Tensor:
        """(M_0, out): ``final(forward(low, high))`` at ``sets.cells[0]`` (``final`` a 3 x 3 convolution), each layer
        computed only where the next one reads it (``fastflow3d.network.cells``); ``sets`` of depth 3."""
        cells = sets.cells[3]
        high_rows = nn.functional.linear(rows_at(high, cells), self.high.weight[:, :, 0, 0], self.high.bias)
        x = torch.cat([rows_at(self.upsampled(low), cells), high_rows], dim=1)
        for depth, conv in zip((2, 1, 0), (*self.fuse, final)):
            x = conv3x3_at(conv, with_zero_row(x), sets.neighbours(depth))
        return x


def local_correlation(features0: torch.Tensor, features1: torch.Tensor, radius: int) -> torch.Tensor:
    """Cost volume (B, (2r + 1)^2, H, W) of two (B, C, H, W) feature maps: channel ``(dy + r) * (2r + 1) + dx + r``
    at cell (y, x) is ``<features0[y, x], features1[y + dy, x + dx]> / sqrt(C)`` for displacements ``|dx|, |dy| <= r``
    cells (zero beyond the border): how well the content of a pc0 cell matches the pc1 cell it would have moved to.
    Built from shifted slices (no unfold), so it exports to ONNX as plain Pad/Slice/Mul/ReduceSum."""
    height, width = features0.shape[-2:]
    padded = nn.functional.pad(features1, (radius, radius, radius, radius))
    scale = features0.shape[1] ** -0.5
    costs = [
        (features0 * padded[:, :, dy : dy + height, dx : dx + width]).sum(dim=1, keepdim=True)
        for dy in range(2 * radius + 1)
        for dx in range(2 * radius + 1)
    ]
    return torch.cat(costs, dim=1) * scale


def centroid_shift(sums0: torch.Tensor, sums1: torch.Tensor, windows) -> torch.Tensor:
    """Sub-pillar motion (B, 4 * len(windows), nx, ny) from the pillar sums (B, 4, nx, ny) of both scans (x, y, z
    summed over a pillar's in-grid points, and their count): per odd window of ``w`` x ``w`` pillars centred on a
    cell, the centroid of pc1's points in it minus that of pc0's (3 channels, metres; 0 unless both scans have points
    there) and whether pc1 has any (1 channel). A pedestrian moves a fifth of a 0.5 m pillar per frame: the pillar
    features see it in no cell, the centroids do."""
    parts = []
    for window in windows:
        pooled0, pooled1 = sums0, sums1
        if window > 1:  # box sums (the mean's divisor cancels in the centroid); zero beyond the border
            pooled0 = F.avg_pool2d(sums0, window, 1, window // 2, count_include_pad=True)
            pooled1 = F.avg_pool2d(sums1, window, 1, window // 2, count_include_pad=True)
        count0, count1 = pooled0[:, 3:], pooled1[:, 3:]
        both = ((count0 > 0) & (count1 > 0)).to(sums0.dtype)
        shift = pooled1[:, :3] / count1.clamp(min=1e-6) - pooled0[:, :3] / count0.clamp(min=1e-6)
        parts += [shift * both, (count1 > 0).to(sums0.dtype)]
    return torch.cat(parts, dim=1)


def pillar_sums(points: torch.Tensor, ids: torch.Tensor, valid: torch.Tensor, slots: int) -> torch.Tensor:
    """(slots, 4): per pillar id the sum of its in-grid points' (P, 3) coordinates and their count."""
    inside = valid[:, None].to(points.dtype)
    return scatter_sum(torch.cat([points * inside, inside], dim=1), ids, slots)


class UNet(nn.Module):
    """Shared encoder on both pseudo-images (B, C, H, W); skips concatenate both scans; output (B, 2C, H, W).

    ``correlation_levels``: the levels (0 = the pseudo-images, k = after encoder stage k) whose skip also carries
    the ``local_correlation`` of the two scans' features over ``correlation_radius`` cells: an explicit
    displacement signal (the matching that the plain concatenation leaves to the convolutions). At level k a cell
    is ``2^k`` pillars wide, so the window covers ``+-radius * 2^k`` pillars. Empty: ZeroFlow's FastFlow3D."""

    def __init__(
        self,
        pillar_channels: int,
        stage_channels,
        stage_blocks,
        norm: str = "batch",
        correlation_levels=(),
        correlation_radius: int = 3,
    ):
        super().__init__()
        widths = [pillar_channels, *stage_channels]
        self.correlation_levels = tuple(sorted({int(level) for level in correlation_levels}))
        self.correlation_radius = int(correlation_radius)
        if any(level < 0 or level >= len(widths) for level in self.correlation_levels):
            raise ValueError(
                f"FastFlow3D: correlation_levels must lie in 0..{len(widths) - 1}, got {list(correlation_levels)}"
            )
        if self.correlation_levels and self.correlation_radius < 1:
            raise ValueError(f"FastFlow3D: correlation_radius must be >= 1, got {correlation_radius}")
        self.encoder = nn.ModuleList(
            encoder_stage(c_in, c_out, n, norm) for c_in, c_out, n in zip(widths[:-1], widths[1:], stage_blocks)
        )
        costs = (2 * self.correlation_radius + 1) ** 2
        # concatenated widths, finest first (both scans, plus the cost volume where there is one)
        skips = [2 * w + (costs if level in self.correlation_levels else 0) for level, w in enumerate(widths)]
        outputs = [2 * w for w in widths]
        self.decoder = nn.ModuleList(
            UpsampleSkip(outputs[i + 1] if i + 1 < len(widths) - 1 else skips[i + 1], skips[i], outputs[i])
            for i in reversed(range(len(skips) - 1))
        )
        self.final = nn.Conv2d(outputs[0], outputs[0], 3, 1, 1)

    def level(self, index: int, image0: torch.Tensor, image1: torch.Tensor) -> torch.Tensor:
        """The skip of level ``index``: both scans' features, and their cost volume at a correlation level."""
        parts = [image0, image1]
        if index in self.correlation_levels:
            parts.append(local_correlation(image0, image1, self.correlation_radius))
        return torch.cat(parts, dim=1)

    def forward(self, image0: torch.Tensor, image1: torch.Tensor, sets: CellSets | None = None) -> torch.Tensor:
        """The decoded image (B, 2C, H, W), or with ``sets`` (``CellSets`` of depth 3 on this grid) its rows
        (M_0, 2C) at ``sets.cells[0]`` only: the same numbers, the full-resolution layers computed where they are
        read (:meth:`UpsampleSkip.at_cells`)."""
        levels = [self.level(0, image0, image1)]
        for index, stage in enumerate(self.encoder, start=1):
            image0, image1 = stage(image0), stage(image1)
            levels.append(self.level(index, image0, image1))
        x = levels[-1]
        *coarse, finest = self.decoder
        for step, skip in zip(coarse, reversed(levels[1:-1])):
            x = step(x, skip)
        if sets is None:
            return self.final(finest(x, levels[0]))
        return finest.at_cells(x, levels[0], sets, self.final)


class PillarEmbedder(nn.Module):
    """Per-point Linear(9 -> C, no bias) + norm (BatchNorm1d(eps 1e-3, momentum 0.01), or a per-point GroupNorm)
    + ReLU, mean per pillar. A training batch with fewer than two points in the grid is normalised with the running
    statistics (batch statistics of one value do not exist); ``StudentModule`` says which samples."""

    def __init__(self, channels: int, norm: str = "batch"):
        super().__init__()
        self.linear = nn.Linear(9, channels, bias=False)
        self.norm = norm_layer(norm, channels, embedder=True)

    def forward(self, features: torch.Tensor, ids: torch.Tensor, valid: torch.Tensor, num_slots: int):
        """Pillar rows (num_slots, C) and per-point embeddings (P, C) from point features (P, 9); batch statistics
        use in-range points only."""
        if torch.compiler.is_exporting() and not self.training and isinstance(self.norm, nn.BatchNorm1d):
            return self.exported(features, ids, num_slots)
        h = self.linear(features)
        batch_norm = self.training and isinstance(self.norm, nn.BatchNorm1d)
        inside = int(valid.sum()) if batch_norm else 0  # training only: one host sync per step, as before
        if batch_norm and inside < 2:  # batch statistics need two values: a degenerate batch (one point
            # in the grid) is normalised with the running ones, as in evaluation, instead of failing
            norm = self.norm
            normed = F.batch_norm(h, norm.running_mean, norm.running_var, norm.weight, norm.bias, False, 0.0, norm.eps)
        elif batch_norm and inside < len(valid):
            normed = torch.zeros_like(h)
            normed[valid] = self.norm(h[valid])
        else:
            normed = self.norm(h)
        points = torch.relu(normed)
        return scatter_mean(points, ids, num_slots), points

    def exported(self, features: torch.Tensor, ids: torch.Tensor, num_slots: int):
        """:meth:`forward` in evaluation as an export traces it: the BatchNorm's running statistics folded into the
        linear layer (one per-point product instead of two passes over the (P, C) embeddings; ONNX Runtime does not
        fold a BatchNormalization after a MatMul itself: 2.3 of 91 ms of the int8 network on a KITTI pair)."""
        norm = self.norm
        scale = norm.weight / torch.sqrt(norm.running_var + norm.eps)
        points = torch.relu(
            F.linear(features, self.linear.weight * scale[:, None], norm.bias - norm.running_mean * scale)
        )
        return scatter_mean(points, ids, num_slots), points


def split_linear(linear: nn.Linear, parts, sets: CellSets | None, ids: torch.Tensor, point_features=None):
    """(P, out): ``linear`` applied per point to ``[parts[0] at its pillar, ..., point_features]`` without
    gathering the parts per point: their part of the weight runs once per pillar (bias included), then one (P, out)
    gather by pillar id, plus the per-point part (if any). ``parts``: (B, C, nx, ny) images, or (M_0, C) rows at
    ``sets.cells[0]`` (the decoded features, ``UNet``); with ``sets`` the pillars are those cells, without them
    every cell of the images. Points outside the grid (the dump id) read a zero row (with ``sets``) or an arbitrary
    one: the caller masks those points."""
    weight, start, pillar = linear.weight, 0, linear.bias
    for part in parts:
        channels = part.shape[1]
        if part.dim() == 4:
            part = image_rows(part) if sets is None else rows_at(part, sets.cells[0])
        pillar, start = nn.functional.linear(part, weight[:, start : start + channels]) + pillar, start + channels
    if sets is None:
        per_point = pillar.index_select(0, ids.clamp(max=pillar.shape[0] - 1))
    else:
        per_point = with_zero_row(pillar).index_select(0, sets.rows[0].index_select(0, ids))
    return per_point if point_features is None else per_point + nn.functional.linear(point_features, weight[:, start:])


class LinearDecoder(nn.Sequential):
    """ZeroFlow's head: Linear(4C + 3 -> 32) + GELU + Linear(32 -> 3) on each point's [pc0 pillar, pc1 pillar,
    decoded pillar features, (``motion`` channels of sub-pillar motion, ``centroid_shift``,) offset of the point from
    its pillar centre]; parameters ``0.*`` and ``2.*`` as ZeroFlow's ``nn.Sequential``."""

    def __init__(self, pillar_channels: int, motion: int = 0):
        super().__init__(nn.Linear(4 * pillar_channels + motion + 3, 32), nn.GELU(), nn.Linear(32, 3))

    def decode(self, parts, sets: CellSets, point_embedding: torch.Tensor, features: torch.Tensor, ids: torch.Tensor):
        """Residual flow (P, 3) from the pillar features ``parts`` (pc0 and pc1 images, decoded rows, see
        ``split_linear``) and the point features (P, 9)."""
        hidden = split_linear(self[0], parts, sets, ids, features[:, 6:9])
        return self[2](self[1](hidden))


class GRUDecoder(nn.Module):
    """DeFlow's voxel-to-point decoder, as its paper describes it: each point's hidden state starts from its
    pillar's feature and a GRU refines it ``iterations`` times with the point's own feature as the input; an MLP
    maps [refined state, point feature] to the flow.

    Here the pillar feature is a linear projection (``hidden`` channels) of [pc0 pillar, pc1 pillar, decoded pillar]
    features (and the ``motion`` channels of ``centroid_shift``), computed per pillar (see ``split_linear``), and the
    point feature is the point's embedding (the pillar embedder's per-point output, C channels) with its offset from
    the pillar centre. The GRU cell is the
    standard one (update gate z, reset gate r, candidate n; ``h <- (1 - z) n + z h``); the input's part of its
    gates is computed once for all iterations. The MLP is Linear(hidden + C + 3 -> 32) + GELU + Linear(32 -> 3).
    """

    def __init__(self, pillar_channels: int, hidden: int, iterations: int, motion: int = 0):
        super().__init__()
        if iterations < 1 or hidden < 1:
            raise ValueError(f"FastFlow3D: gru_iterations and gru_channels must be >= 1, got {iterations}, {hidden}")
        point = pillar_channels + 3
        self.iterations = int(iterations)
        self.initial = nn.Linear(4 * pillar_channels + motion, hidden)
        self.input_gates = nn.Linear(point, 3 * hidden)
        self.hidden_gates = nn.Linear(hidden, 3 * hidden)
        self.flow = nn.Sequential(nn.Linear(hidden + point, 32), nn.GELU(), nn.Linear(32, 3))

    def decode(self, parts, sets: CellSets, point_embedding: torch.Tensor, features: torch.Tensor, ids: torch.Tensor):
        """Residual flow (P, 3) from the pillar features ``parts`` (pc0 and pc1 images, decoded rows, see
        ``split_linear``), the per-point embeddings (P, C) and the point features (P, 9)."""
        point = torch.cat([point_embedding, features[:, 6:9]], dim=1)
        # the input's part of the gates once; the z and r gates' hidden bias folded into it (fewer passes per step)
        x_gates = self.input_gates(point)
        h = split_linear(self.initial, parts, sets, ids).to(x_gates.dtype)  # bf16 under autocast, as the gates
        hidden = h.shape[1]
        x_zr = x_gates[:, : 2 * hidden] + self.hidden_gates.bias[: 2 * hidden].to(x_gates.dtype)
        x_n = x_gates[:, 2 * hidden :]
        weight_zr, weight_n = self.hidden_gates.weight[: 2 * hidden], self.hidden_gates.weight[2 * hidden :]
        bias_n = self.hidden_gates.bias[2 * hidden :]
        for _ in range(self.iterations):
            z, r = torch.sigmoid(torch.addmm(x_zr, h, weight_zr.T)).chunk(2, dim=1)
            n = torch.tanh(torch.addcmul(x_n, r, torch.addmm(bias_n, h, weight_n.T)))
            h = torch.lerp(n, h, z)  # (1 - z) n + z h
        return self.flow(torch.cat([h, point], dim=1))


class FastFlow3D(nn.Module):
    """FastFlow3D on flat batches. ``forward(pc0, batch0, pc1, batch1, batch_size)`` -> (residual (P0, 3), valid).

    pc0 (P0, 3) ego-compensated, pc1 (P1, 3), batch0/batch1 int64 sample indices in ``[0, batch_size)``.

    Every argument but ``norm`` and the decoder's is required: the settings live in one place,
    ``conf/model/*.yaml`` (``fastflow3d.yaml`` is FastFlow3D as ZeroFlow implements it; the others extend it), and a
    checkpoint carries them all (checkpoints written before an argument existed get its default: ``norm="batch"``,
    ``decoder="linear"``, ZeroFlow's FastFlow3D). ``decoder``: ``linear`` (ZeroFlow's head) or ``gru``
    (``GRUDecoder`` with ``gru_channels`` hidden channels and ``gru_iterations`` refinements).
    ``correlation_levels`` / ``correlation_radius``: the UNet levels that also carry a local cost volume of the two
    scans (``UNet``, ``local_correlation``); empty (the default, and what older checkpoints get) is ZeroFlow's
    network exactly. ``motion_windows``: odd window sizes (pillars) at which the decoder also sees
    ``centroid_shift``, the two scans' centroid difference (empty, the default and what older checkpoints get: none).
    """

    def __init__(
        self,
        *,
        x_range: tuple[float, float],
        y_range: tuple[float, float],
        z_range: tuple[float, float],
        cell: float,
        pillar_channels: int,
        stage_channels: tuple[int, ...],
        stage_blocks: tuple[int, ...],
        norm: str = "batch",
        decoder: str = "linear",
        gru_iterations: int = 4,
        gru_channels: int = 32,
        correlation_levels: tuple[int, ...] = (),
        correlation_radius: int = 3,
        motion_windows: tuple[int, ...] = (),
    ):
        super().__init__()
        self.motion_windows = tuple(int(window) for window in motion_windows)
        if any(window < 1 or window % 2 == 0 for window in self.motion_windows):
            raise ValueError(f"FastFlow3D: motion_windows must be odd sizes >= 1, got {list(motion_windows)}")
        if norm not in NORMS:
            raise ValueError(f"FastFlow3D: norm must be one of {', '.join(NORMS)}, got {norm!r}")
        if decoder not in DECODERS:
            raise ValueError(f"FastFlow3D: decoder must be one of {', '.join(DECODERS)}, got {decoder!r}")
        if len(stage_channels) != len(stage_blocks):
            raise ValueError(f"FastFlow3D: {len(stage_channels)} stage_channels but {len(stage_blocks)} stage_blocks")
        self.grid = Grid(tuple(x_range), tuple(y_range), tuple(z_range), float(cell))
        factor = 2 ** len(stage_channels)
        if self.grid.nx % factor or self.grid.ny % factor:
            raise ValueError(f"FastFlow3D: grid {self.grid.nx}x{self.grid.ny} not divisible by {factor}")
        self.embedder = PillarEmbedder(pillar_channels, norm)
        self.unet = UNet(
            pillar_channels,
            tuple(stage_channels),
            tuple(stage_blocks),
            norm,
            tuple(correlation_levels),
            int(correlation_radius),
        )
        motion = 4 * len(self.motion_windows)
        if decoder == "linear":
            self.head = LinearDecoder(pillar_channels, motion)
        else:
            self.head = GRUDecoder(pillar_channels, int(gru_channels), int(gru_iterations), motion)
        self.to(memory_format=torch.channels_last)

    def embed(self, points: torch.Tensor, batch: torch.Tensor, batch_size: int):
        """Pseudo-image (B, C, nx, ny) (channels_last), per-point features (P, 9), pillar ids, in-range mask,
        per-point embeddings (P, C) of one scan, and its pillar sums (B, 4, nx, ny) (``pillar_sums``; None without
        ``motion_windows``)."""
        features, ids, valid = voxelize(points, batch, self.grid, batch_size)
        slots, (nx, ny) = batch_size * self.grid.nx * self.grid.ny + 1, (self.grid.nx, self.grid.ny)
        rows, embedding = self.embedder(features, ids, valid, slots)
        sums = None
        if self.motion_windows:
            sums = to_pseudo_image(pillar_sums(points, ids, valid, slots), batch_size, nx, ny)
        return to_pseudo_image(rows, batch_size, nx, ny), features, ids, valid, embedding, sums

    def forward(
        self, pc0: torch.Tensor, batch0: torch.Tensor, pc1: torch.Tensor, batch1: torch.Tensor, batch_size: int = 1
    ):
        image0, features0, ids0, valid0, embedding0, sums0 = self.embed(pc0, batch0, batch_size)
        image1, *_, sums1 = self.embed(pc1, batch1, batch_size)
        # the decoder's last layers where they are read, in float32 (fastflow3d.network.cells says why not otherwise)
        dense = torch.compiler.is_exporting() or torch.is_autocast_enabled(pc0.device.type)
        sets = None if dense else CellSets(ids0, batch_size, self.grid.nx, self.grid.ny, 3)
        decoded = self.unet(image0, image1, sets)
        parts = (image0, image1, decoded)
        if self.motion_windows:
            parts += (centroid_shift(sums0.float(), sums1.float(), self.motion_windows),)
        residual = self.head.decode(parts, sets, embedding0, features0, ids0)
        return torch.where(valid0[:, None], residual, torch.zeros_like(residual)), valid0
