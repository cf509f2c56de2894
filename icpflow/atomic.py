"""Atomic file writes: a result file is either absent, its previous version, or complete; never half-written.

Every file this project writes as a result (shards, ``index.json``, metrics, checkpoints, exports, pictures, flows)
goes through :func:`atomic_path`: the writer fills a temporary file in the target's folder, which is then fsynced,
renamed over the target and the folder fsynced. On any exception the temporary file is removed and the target is
left as it was; an ``OSError`` (a full disk, no permission, an I/O error) becomes one :class:`WriteError` naming the
target and the cause.
"""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterator
from pathlib import Path


class WriteError(OSError):
    """A file could not be written (disk full, no permission, I/O error). The message is one line naming it."""


def temporary_name(path: Path) -> Path:
    """A fresh temporary name next to ``path``: ``<name>.tmp-<random><suffix>`` (unique across processes and hosts
    sharing the folder; the suffix is kept for writers that pick the format from it)."""
    return path.with_name(f"{path.name}.tmp-{uuid.uuid4().hex}{path.suffix}")


def fsync_path(path: Path) -> None:
    """Flush a file's or a folder's content to the disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, make_parents: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to ``path`` for the caller to write; on a clean exit it is fsynced and renamed over
    ``path`` (then the folder is fsynced); on an exception it is removed and ``path`` is untouched.

    ``make_parents`` creates the target's folder first. A writer that does not create the file (an error it did not
    raise) leaves ``path`` untouched too: the rename fails with FileNotFoundError.
    """
    path = Path(path)
    if make_parents:
        path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(path)
    try:
        yield tmp
        fsync_path(tmp)
        os.replace(tmp, path)
        fsync_path(path.parent)
    except WriteError:
        raise
    except OSError as error:
        raise WriteError(f"{path}: cannot write ({error.strerror or error})") from None
    finally:
        tmp.unlink(missing_ok=True)


def write_text_atomic(path: str | os.PathLike, text: str, *, make_parents: bool = False) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path, make_parents=make_parents) as tmp:
        tmp.write_text(text, encoding="utf-8")
