"""Deterministic split of the dataset into shards, and of the shards between jobs."""

from __future__ import annotations


def plan_shards(
    size: int, shard_size: int, limit: int | None = None, shard_index: int = 0, num_shards: int = 1
) -> list[tuple[int, list[int]]]:
    """``[(shard number, [dataset indices])]`` for job ``shard_index`` of ``num_shards``.

    Shard s holds indices ``s*shard_size .. (s+1)*shard_size - 1`` (clipped to ``limit``); job i takes the shards
    with ``s % num_shards == i``, so the union of all jobs is the whole plan and the files never collide.
    """
    if shard_size < 1:
        raise ValueError(f"shard_size must be >= 1, got {shard_size}")
    if not 0 <= shard_index < num_shards:
        raise ValueError(f"shard_index must be in 0..{num_shards - 1}, got {shard_index}")
    total = size if limit is None else min(size, limit)
    shards = [
        (s, list(range(start, min(start + shard_size, total)))) for s, start in enumerate(range(0, total, shard_size))
    ]
    return [shard for shard in shards if shard[0] % num_shards == shard_index]
