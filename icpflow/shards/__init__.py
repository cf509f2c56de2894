"""Pseudo-label shards: HDF5 files of labelled frame pairs (schema, atomic writer, reader, verification)."""

from icpflow.shards.reader import ShardDataset
from icpflow.shards.schema import SCHEMA_VERSION
from icpflow.shards.verify import ShardError, verify_shard
from icpflow.shards.writer import write_index, write_shard

__all__ = ["SCHEMA_VERSION", "ShardDataset", "ShardError", "verify_shard", "write_index", "write_shard"]
