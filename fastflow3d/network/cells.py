"""Convolutions computed only at the cells whose outputs are read: the occupied pillars of pc0 and their neighbours.

The full-resolution layers of the UNet's decoder (two 3 x 3 convolutions and the final one) feed only the head,
which reads the decoded image at the pillars of pc0's points: in the small model about 3.5 % of the 128 x 128 cells.
The final convolution is needed at those cells (``targets``), the one before it at their 3 x 3 neighbourhood, the one
before that at the 5 x 5 one: :class:`CellSets` holds these nested dilations, and :func:`conv3x3_at` computes a 3 x 3
convolution at one set from its input rows at the next, as a gather of each cell's nine neighbours and one matrix
product (exported as Gather / MatMul). The result is the dense network's at those cells, up to float rounding
(``tests/fastflow3d/network/test_model.py``): every neighbour that a set's cell reads lies in the next set, and a
neighbour outside the grid reads a zero row, as the dense convolution's zero padding.

Float32 training and eager inference run this (``FastFlow3D.forward``). Under autocast (bf16) the dense layers run:
each tap's product is rounded to bf16 before the taps are summed, where the dense convolution rounds once, the seeds
did not rule out a cost to accuracy, and the step there was only 1.07x quicker (BENCHMARKS.md, "Every CPU"). An export
keeps the dense layers too: in ONNX Runtime the gathers and products cost about what the skipped convolutions saved,
and they would stay float32 in the int8 network.

Rows are flat cell indices ``b * nx * ny + x * ny + y`` (the pillar ids of ``fastflow3d.network.voxelize``; the dump
id ``B * nx * ny`` is the points outside the grid), as the channels_last pseudo-images lay them out.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from fastflow3d.network.scatter import scatter_sum


class CellSets:
    """The cells of ``targets`` (pillar ids (P,), the dump id allowed) on a (B, nx, ny) grid and their dilations by
    1, ..., ``depth`` cells (3 x 3 steps, within the grid).

    ``cells[k]`` (M_k,) int64: the flat indices of dilation k, ascending; ``rows[k]`` (B * nx * ny + 1,) int64: each
    flat index's row in ``cells[k]``, ``M_k`` (the zero row a caller appends) for cells outside it and for the dump
    id; ``neighbours(k)`` (M_k, 9): the rows in dilation k + 1 of each cell's 3 x 3 neighbourhood, in the order of
    a ``Conv2d`` weight's (ky, kx), ``M_{k+1}`` beyond the grid."""

    def __init__(self, targets: torch.Tensor, batch_size: int, nx: int, ny: int, depth: int):
        self.shape, slots = (batch_size, nx, ny), batch_size * nx * ny
        counts = scatter_sum(targets.new_ones((targets.shape[0], 1), dtype=torch.float32), targets, slots + 1)
        image = (counts[:slots, 0] > 0).to(torch.float32).reshape(batch_size, 1, nx, ny)
        self.cells, self.rows = [], []
        for _ in range(depth + 1):
            member = torch.cat([image.reshape(-1) > 0, member_of_none(image)])  # the dump id: in no set
            cells = torch.nonzero(member).reshape(-1)
            # a member's row is its rank among the members (no scatter: one in an export would be one more of the
            # pillar sums that a one-thread session rewrites, fastflow3d.artifact.sequential_scatter)
            rank = torch.cumsum(member.to(torch.int64), 0) - 1
            self.cells.append(cells)
            self.rows.append(torch.where(member, rank, cells.shape[0]))
            image = F.max_pool2d(image, 3, 1, 1)

    def neighbours(self, k: int) -> torch.Tensor:
        """(M_k, 9) rows in ``cells[k + 1]`` of the 3 x 3 neighbours of each cell of ``cells[k]``."""
        batch_size, nx, ny = self.shape
        cells = self.cells[k]
        taps = torch.arange(9, device=cells.device)  # an op, not a tensor constant (an export's .pt2 holds none)
        dx, dy = taps // 3 - 1, taps % 3 - 1
        x, y = (cells % (nx * ny)) // ny, cells % ny
        xs, ys = x[:, None] + dx, y[:, None] + dy
        inside = (xs >= 0) & (xs < nx) & (ys >= 0) & (ys < ny)
        flat = torch.where(inside, cells[:, None] + dx * ny + dy, batch_size * nx * ny)  # beyond: the dump id
        return self.rows[k + 1][flat]


def member_of_none(image: torch.Tensor) -> torch.Tensor:
    """(1,) False: the dump id's entry of a set's membership (made from ``image`` so that it follows its device)."""
    return image.reshape(-1)[:1] < 0


def with_zero_row(rows: torch.Tensor) -> torch.Tensor:
    """(M + 1, C): ``rows`` (M, C) and a zero row, the one that cells outside a set and beyond the grid read."""
    return torch.cat([rows, rows.new_zeros((1, rows.shape[1]))], dim=0)


def conv3x3_at(conv: nn.Conv2d, inputs: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """(M, C_out): ``conv`` (3 x 3, stride 1, padding 1) at M cells from ``inputs`` (R + 1, C_in), the rows of the
    cells it reads with a zero row last, and ``neighbours`` (M, 9) their rows in ``inputs``. One gather and product
    per tap, summed: the (M, 9 C_in) matrix of all taps at once and its gradient cost 1.15x more, in memory traffic
    (BENCHMARKS.md, "Every CPU")."""
    out = conv.bias
    for tap, rows in enumerate(neighbours.T):
        out = F.linear(inputs.index_select(0, rows), conv.weight[:, :, tap // 3, tap % 3]) + out
    return out


def image_rows(image: torch.Tensor) -> torch.Tensor:
    """(B * nx * ny, C) rows of a (B, C, nx, ny) image, by flat cell index: a view for a channels_last image."""
    return image.permute(0, 2, 3, 1).reshape(-1, image.shape[1])


def rows_at(image: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """(M, C): the rows of a (B, C, nx, ny) image at flat cell indices ``cells``."""
    return image_rows(image).index_select(0, cells)
