"""Checks that a shard file is complete and valid (the resume logic redoes any shard that fails them)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from icpflow.core.stops import raise_stop_behind
from icpflow.shards.access import ShardError, open_shard, shard_array, shard_group
from icpflow.shards.schema import CLOUD, FILE_ATTRS, OPTIONAL, REQUIRED, SAMPLE_ATTRS, SCHEMA_VERSION, group_name


def _check_array(path, name, key, data, spec, counts):
    dtype, trail = spec
    if data.dtype != dtype:
        raise ShardError(f"{path}: {name}/{key} is {data.dtype}, expected {dtype}")
    if isinstance(trail, tuple):
        expected = trail
    else:
        n = counts[CLOUD.get(key, "pc0")]
        expected = (n,) if trail is None else (n, trail)
    if data.shape != expected:
        raise ShardError(f"{path}: {name}/{key} has shape {data.shape}, expected {expected}")
    values = data[()]  # reads every chunk: a truncated or corrupt file fails here
    if np.issubdtype(values.dtype, np.floating) and not np.isfinite(values).all():
        bad = int((~np.isfinite(values)).sum())
        raise ShardError(f"{path}: {name}/{key} holds {bad} non-finite value(s) (NaN or Inf)")


def verify_shard(path: Path, config_hash: str | None = None, num_samples: int | None = None) -> int:
    """Raise :class:`ShardError` unless ``path`` is a complete shard (optionally of ``config_hash`` and size).

    Returns the number of samples.
    """
    path = Path(path)
    if not os.path.lexists(path):
        raise ShardError(f"{path}: missing")
    try:
        with open_shard(path) as f:
            missing = [a for a in FILE_ATTRS if a not in f.attrs]
            if missing:
                raise ShardError(f"{path}: file attributes missing: {', '.join(missing)}")
            if int(f.attrs["schema_version"]) != SCHEMA_VERSION:
                raise ShardError(f"{path}: schema version {f.attrs['schema_version']}, expected {SCHEMA_VERSION}")
            if config_hash is not None and f.attrs["config_hash"] != config_hash:
                raise ShardError(f"{path}: made by config {f.attrs['config_hash']}, expected {config_hash}")
            count = int(f.attrs["num_samples"])
            if num_samples is not None and count != num_samples:
                raise ShardError(f"{path}: holds {count} samples, expected {num_samples}")
            for position in range(count):
                name = group_name(position)
                group = shard_group(path, f, name)
                if group is None:
                    raise ShardError(f"{path}: group {name} missing")
                arrays = {key: shard_array(path, group, key) for key in (*REQUIRED, *OPTIONAL)}
                for key in REQUIRED:
                    if arrays[key] is None:
                        raise ShardError(f"{path}: {name}/{key} missing")
                lost = [a for a in SAMPLE_ATTRS if a not in group.attrs]
                if lost:
                    raise ShardError(f"{path}: {name} attributes missing: {', '.join(lost)}")
                counts = {"pc0": arrays["pc0"].shape[0], "pc1": arrays["pc1"].shape[0]}
                for key, spec in {**REQUIRED, **OPTIONAL}.items():
                    if arrays[key] is not None:
                        _check_array(path, name, key, arrays[key], spec, counts)
            return count
    except ShardError:
        raise
    except Exception as error:  # h5py raises OSError/KeyError/RuntimeError on damaged files
        raise_stop_behind(error)
        raise ShardError(f"{path}: unreadable ({type(error).__name__}: {str(error).splitlines()[0][:160]})") from None
