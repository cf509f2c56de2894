"""The one way a reader of the project opens a file it was handed (a scan, poses, an export's metadata, a manifest, a
config, a trajectory, a record): a regular file, of a size bounded before it is read.

A FIFO would hang the reader on its first read, a character device (``/dev/zero``, a link to it) would read until
memory runs out, a folder cannot be read; each is refused in one line naming the path (:class:`NotAFile`, a
ValueError, as a reader's other one-line errors), before it is opened. A link to a regular file is the file. Text
files (metadata, manifests, configs, poses) are read whole only up to :data:`MAX_TEXT_BYTES`. Shards have their own
door with HDF5's checks besides (``icpflow.shards.access``).
"""

from __future__ import annotations

import os
import stat

#: bytes: the largest text file a reader reads whole (a poses file of a 100,000-scan drive is about 20 MB)
MAX_TEXT_BYTES = 64 << 20

KINDS = (
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISDIR, "a folder"),
)


class NotAFile(ValueError):
    """A path that is not a regular file, or a file larger than a reader takes. The message is one line."""


def not_a_file(path: str | os.PathLike) -> str | None:
    """The line :func:`regular_file` refuses ``path`` with where something other than a regular file is there (a
    FIFO, a device, a folder); None where it is a regular file or nothing is there (the caller's "not found")."""
    try:
        regular_file(path)
    except NotAFile as error:
        return str(error)
    except FileNotFoundError:
        pass
    return None


def regular_file(path: str | os.PathLike) -> os.stat_result:
    """The stat of ``path`` (a link followed) where it is a regular file; :class:`NotAFile` where it is something
    else; FileNotFoundError where nothing is there. Nothing is opened."""
    info = os.stat(path)
    if not stat.S_ISREG(info.st_mode):
        kind = next((name for test, name in KINDS if test(info.st_mode)), "not a regular file")
        raise NotAFile(f"{path}: {kind}, not a regular file; give a file")
    return info


def read_bytes(path: str | os.PathLike, limit: int = MAX_TEXT_BYTES) -> bytes:
    """The bytes of the regular file ``path``, refused (:class:`NotAFile`) where it holds more than ``limit``."""
    size = regular_file(path).st_size
    if size > limit:
        raise NotAFile(f"{path}: {size} bytes, more than the {limit} a file of this kind may hold")
    with open(path, "rb") as handle:
        data = handle.read(limit + 1)  # bounded even where the file grows meanwhile
    if len(data) > limit:
        raise NotAFile(f"{path}: more than the {limit} bytes a file of this kind may hold")
    return data


def read_text(path: str | os.PathLike, limit: int = MAX_TEXT_BYTES) -> str:
    """The UTF-8 text of the regular file ``path`` (:func:`read_bytes`); UnicodeDecodeError where it is not UTF-8
    (each reader says what it expected instead)."""
    return read_bytes(path, limit).decode("utf-8")
