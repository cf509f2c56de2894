"""Scatter reductions over pillar ids written with ``scatter_reduce`` (exports to ONNX with the dynamo exporter).

``ids`` (P,) int64 index rows of an output with ``num_slots`` rows; ``index_add`` is avoided on purpose: the legacy
ONNX exporter mis-exports it silently (see NOTES.md). New tensors are made with ``Tensor.new_zeros`` /
``new_ones``, which a TorchScript trace records without a device, so a traced model runs on the device of its
inputs (``torch.zeros(..., device=x.device)`` would bake the tracing device in).
"""

import torch


def scatter_sum(values: torch.Tensor, ids: torch.Tensor, num_slots: int) -> torch.Tensor:
    """Row sums: (num_slots, C) with ``out[k] = sum of values[p] over p with ids[p] == k``; values (P, C).

    Exported (ONNX, torch.export) as a scatter along the last axis of the transposed rows: ONNX Runtime's
    ScatterElements runs it 2.2x quicker than along the first (50k points x 33 channels, 2 threads), while PyTorch's
    eager training step is 10 % slower that way, so eager code keeps the first axis (docs/history.md, "ONNX Runtime's
    pillar scatters, a quicker voxel grid"); the sums are the same. Not ``ScatterND`` with ``reduction="add"`` (an
    accumulating ``index_put``), though 12x quicker (60k points x 33 channels, 1 thread): ONNX Runtime splits its
    updates over its threads without atomics, so duplicate ids race (sums off by up to 1.0 with 2 threads;
    onnxruntime's GitHub issue 18048; docs/history.md, "ScatterND: tried, not kept"). A session of one thread cannot
    race, and gets ScatterND at load: ``fastflow3d.artifact.sequential_scatter``."""
    if torch.compiler.is_exporting():
        out = values.new_zeros((values.shape[1], num_slots))
        index = ids[None, :].expand(values.shape[1], -1)
        return out.scatter_reduce(1, index, values.T, reduce="sum", include_self=True).T
    out = values.new_zeros((num_slots, values.shape[1]))
    index = ids[:, None].expand(-1, values.shape[1])
    return out.scatter_reduce(0, index, values, reduce="sum", include_self=True)


def scatter_mean(values: torch.Tensor, ids: torch.Tensor, num_slots: int) -> torch.Tensor:
    """Row means (num_slots, C) of values (P, C) grouped by ``ids``; rows without any point are 0.

    Exported as two sums, of the values and of ones (the same sums): the (P, C + 1) concatenation of the eager
    step costs ONNX Runtime about 3 of the int8 network's 60 ms on a pair of 60k-point scans (docs/history.md, "The
    network: the pillar sums on one thread (point 3)")."""
    ones = values.new_ones((values.shape[0], 1))
    if torch.compiler.is_exporting():
        return scatter_sum(values, ids, num_slots) / scatter_sum(ones, ids, num_slots).clamp(min=1.0)
    summed = scatter_sum(torch.cat([values, ones], dim=1), ids, num_slots)
    counts = summed[:, -1:].clamp(min=1.0)
    return summed[:, :-1] / counts


def to_pseudo_image(pillar_values: torch.Tensor, batch_size: int, nx: int, ny: int) -> torch.Tensor:
    """(B * nx * ny + 1, C) pillar rows (last row is the dump slot) -> pseudo-image (B, C, nx, ny), a view of the
    rows in channels_last memory format (no copy)."""
    channels = pillar_values.shape[1]
    image = pillar_values[: batch_size * nx * ny].reshape(batch_size, nx, ny, channels)
    return image.permute(0, 3, 1, 2)
