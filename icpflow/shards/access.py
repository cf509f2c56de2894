"""The one way a shard file and its arrays are opened, for every reader (training, evaluation, verification, the
student's contract): a shard holds its own data, and what it claims is bounded before anything is allocated.

Refused, each in one line naming the file and the array (:class:`ShardError`): a shard that is a symbolic link or
not a regular file (a FIFO, a device: a read would hang or leave the label folder); a group or array that is an
HDF5 external or soft link, an array stored outside the file (HDF5 external storage, e.g. ``/etc/passwd`` read as
numbers) or a virtual dataset over other files; an array of more values than ``icpflow.core.frame_pair.MAX_POINTS``
points of 3 values (a 14 MB file of zeros can claim 3e8 points) or, uncompressed, more bytes than the file holds.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

import h5py

from icpflow.core.frame_pair import MAX_POINTS
from icpflow.shards.schema import SCHEMA_VERSION


class ShardError(ValueError):
    """A shard is missing, truncated, corrupt, unsafe or made by another config. The message is one line."""


def open_shard(path: str | os.PathLike) -> h5py.File:
    """``path`` opened read-only, after the file checks of the module docstring and of its schema version (a shard
    of another version of ``label.py`` is refused by every reader; FileNotFoundError: none)."""
    path = Path(path)
    info = os.lstat(path)
    if stat.S_ISLNK(info.st_mode):
        raise ShardError(f"{path}: a symbolic link (to {os.readlink(path)}); a shard is a file of its label folder")
    if not stat.S_ISREG(info.st_mode):
        raise ShardError(f"{path}: not a regular file (a FIFO, device or folder); a shard is a file")
    handle = h5py.File(path, "r")
    version = handle.attrs.get("schema_version")
    if version is None:
        handle.close()
        raise ShardError(f"{path}: no schema version: not a shard written by label.py")
    if version != SCHEMA_VERSION:
        handle.close()
        raise ShardError(
            f"{path}: schema version {version}, expected {SCHEMA_VERSION} (written by another version of label.py); "
            "relabel it with this one"
        )
    return handle


def _member(path: Path, parent: h5py.Group, key: str, where: str):
    """``parent[key]`` (None where absent), refused where it is a link (external or soft)."""
    link = parent.get(key, getlink=True)
    if link is None:
        return None
    if isinstance(link, h5py.ExternalLink):
        raise ShardError(f"{path}: {where} is an external link to {link.filename}:{link.path}; a shard holds its data")
    if isinstance(link, h5py.SoftLink):
        raise ShardError(f"{path}: {where} is a link to {link.path}; a shard holds each array once, by name")
    return parent[key]


def shard_group(path: Path, handle: h5py.File, name: str) -> h5py.Group | None:
    """The sample group ``name`` of an open shard (None where absent; refused where a link or not a group)."""
    group = _member(Path(path), handle, name, name)
    if group is not None and not isinstance(group, h5py.Group):
        raise ShardError(f"{path}: {name} is not a group of arrays")
    return group


def shard_array(path: Path, group: h5py.Group, key: str) -> h5py.Dataset | None:
    """The array ``key`` of a sample group (None where absent), checked as the module docstring says; nothing of
    it is read."""
    where = f"{group.name.lstrip('/')}/{key}"
    data = _member(Path(path), group, key, where)
    if data is None:
        return None
    if not isinstance(data, h5py.Dataset):
        raise ShardError(f"{path}: {where} is not an array")
    if data.is_virtual:
        sources = sorted({source.file_name for source in data.virtual_sources()})
        raise ShardError(f"{path}: {where} is a virtual dataset over {', '.join(sources)}; a shard holds its data")
    if data.external:
        raise ShardError(f"{path}: {where} is stored outside the shard, in {data.external[0][0]!r}; refused")
    if data.dtype.itemsize > 8 or data.dtype.kind not in "biuf":  # shards hold plain numbers (schema.py)
        raise ShardError(f"{path}: {where} holds {data.dtype} values, not the plain numbers of a shard")
    values = int(data.size)
    if values > 3 * MAX_POINTS:
        raise ShardError(f"{path}: {where} claims {data.shape} values, over the cap of {MAX_POINTS} points")
    if data.compression is None and values * data.dtype.itemsize > os.path.getsize(path):
        raise ShardError(f"{path}: {where} claims {data.shape} values, more than the file holds")
    return data
