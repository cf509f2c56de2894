"""Atomic writes: shards, ``index.json`` and the ``failures.jsonl`` manifest never appear half-written."""

from __future__ import annotations

import io
import json
from pathlib import Path

import h5py
import numpy as np

import icpflow
from icpflow.core.atomic import atomic_path, write_text_atomic
from icpflow.shards.schema import COMPRESSIONS, SCHEMA_VERSION, group_name


def write_shard(path: Path, samples: list[dict], config_yaml: str, config_hash: str, compression: str | None = None):
    """Write ``samples`` (dicts of arrays plus an ``attrs`` dict, see ``schema``) to ``path`` atomically.

    The HDF5 file is built in memory, then written through ``icpflow.core.atomic``, so a full disk or another write
    error is one :class:`~icpflow.core.atomic.WriteError` (HDF5 never meets it half-way through a file). Every array
    carries Fletcher-32 checksums; ``compression`` is an HDF5 filter (``gzip``, ``lzf``), ``none`` or None.
    """
    if compression is not None and compression not in COMPRESSIONS:
        raise ValueError(f"write_shard: compression must be one of {', '.join(COMPRESSIONS)}, got {compression!r}")
    opts = {"fletcher32": True}  # per-chunk checksums: a corrupted byte fails verification
    if compression not in (None, "none"):
        opts["compression"] = compression
    buffer = io.BytesIO()
    with h5py.File(buffer, "w") as f:
        f.attrs.update(
            config=config_yaml,
            config_hash=config_hash,
            package_version=icpflow.__version__,
            schema_version=SCHEMA_VERSION,
            num_samples=len(samples),
        )
        for position, sample in enumerate(samples):
            group = f.create_group(group_name(position))
            for key, value in sample.items():
                if key == "attrs":
                    group.attrs.update(value)
                elif value is not None:
                    value = np.asarray(value)
                    group.create_dataset(key, data=value, **(opts if value.size else {}))
    with atomic_path(path) as tmp:
        tmp.write_bytes(buffer.getbuffer())


def write_index(path: Path, index: dict) -> None:
    """``index.json``: ``{"config_hash", "shards": [{"file", "samples": [{"sample_id", "index", "n0", "n1"}]}]}``."""
    write_text_atomic(path, json.dumps(index, indent=1, sort_keys=True))


def write_failures(path: Path, failures: list[dict]) -> None:
    """``failures.jsonl``: one ``{"index", "sample_id", "file", "reason"}`` record per line, sorted by index."""
    lines = [json.dumps(record, sort_keys=True) for record in sorted(failures, key=lambda r: r["index"])]
    write_text_atomic(path, "".join(line + "\n" for line in lines))
