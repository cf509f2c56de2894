"""Atomic file writes: a result file is either absent, its previous version, or complete; never half-written.

Every file this project writes as a result (shards, ``index.json``, metrics, checkpoints, exports, pictures, flows)
goes through :func:`atomic_path`: the writer fills a temporary file in the target's folder, which is then fsynced,
renamed over the target and the folder fsynced. On any exception the temporary file is removed and the target is
left as it was; an ``OSError`` (a full disk, no permission, an I/O error) becomes one :class:`WriteError` naming the
target and the cause. A result made of several files (an export) goes through :func:`atomic_directory`: built in a
temporary folder, then swapped in whole. A folder that one run at a time may write (a training run's ``out_dir``) is
held with :func:`folder_lock`.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path


class WriteError(OSError):
    """A file could not be written (disk full, no permission, I/O error). The message is one line naming it."""


#: bytes of a file name on the filesystems we write to (ext4, xfs, btrfs, tmpfs, APFS, NTFS in UTF-16 units)
NAME_MAX = 255


def temporary_name(path: Path) -> Path:
    """A fresh temporary name next to ``path``: ``<name>.tmp-<random><suffix>`` (unique across processes and hosts
    sharing the folder; the suffix is kept for writers that pick the format from it). A name too long to take the
    41 or so bytes more is cut first, so that any name that can be written has a temporary one."""
    tail = f".tmp-{uuid.uuid4().hex}{path.suffix}"
    name = path.name.encode()[: NAME_MAX - len(tail.encode())].decode(errors="ignore")
    return path.with_name(f"{name}{tail}")


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
    tmp = temporary_name(path)
    try:
        if make_parents:
            path.parent.mkdir(parents=True, exist_ok=True)
        yield tmp
        fsync_path(tmp)
        os.replace(tmp, path)
        fsync_path(path.parent)
    except WriteError:
        raise
    except OSError as error:
        raise WriteError(f"{path}: cannot write ({error.strerror or error})") from None
    finally:
        with contextlib.suppress(OSError):  # absent, or a read-only folder: nothing to remove
            tmp.unlink()


def write_text_atomic(path: str | os.PathLike, text: str, *, make_parents: bool = False) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path, make_parents=make_parents) as tmp:
        tmp.write_text(text, encoding="utf-8")


def _exchange(a: Path, b: Path) -> bool:
    """Swap two existing paths in one step (Linux ``renameat2(RENAME_EXCHANGE)``); False where that is unavailable
    (another system or C library, or a filesystem without it)."""
    libc = ctypes.CDLL(None, use_errno=True)
    renameat2 = getattr(libc, "renameat2", None)
    if renameat2 is None:
        return False
    at_fdcwd, rename_exchange = -100, 2
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP):
        return False
    raise OSError(code, os.strerror(code), str(b))


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike) -> Iterator[Path]:
    """Yield an empty temporary folder next to ``path`` for the caller to fill; on a clean exit its files are fsynced
    and it replaces ``path`` whole (an existing folder is exchanged with it in one step where the system allows,
    else renamed aside first, then removed); on an exception it is removed and ``path`` is untouched. Readers see
    the old folder or the new one, never a mixture; an ``OSError`` becomes one :class:`WriteError` naming ``path``."""
    path = Path(path)
    tmp = temporary_name(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.mkdir()
        yield tmp
        for child in tmp.iterdir():
            fsync_path(child)
        fsync_path(tmp)
        if not path.exists():
            os.rename(tmp, path)
        elif not _exchange(tmp, path):  # tmp now holds the old folder when the exchange worked
            aside = temporary_name(path)
            os.rename(path, aside)
            os.rename(tmp, path)
            os.rename(aside, tmp)
        fsync_path(path.parent)
    except WriteError as error:  # a file inside: named as in its final place
        raise WriteError(str(error).replace(str(tmp), str(path))) from error.__context__
    except OSError as error:
        raise WriteError(f"{path}: cannot write ({error.strerror or error})") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


class FolderInUse(RuntimeError):
    """Another live process holds a folder's lock (:func:`folder_lock`). The message is one line naming it."""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, another user's
        return True
    return True


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike, what: str) -> Iterator[Path]:
    """Hold ``<folder>/.lock`` for the block: one run writes a folder at a time. The lock file holds the pid and
    host of its holder; a second holder on this host is refused with :class:`FolderInUse` naming the pid while
    that process lives, and a lock left by a dead process (a kill -9, a crash) is taken over. ``what`` names the
    holder in the message (``train.py``). The lock file is removed when the block ends, if it is still ours.
    On another host's lock nothing can be checked: it is refused, naming the host (remove the file if that run is
    gone)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / ".lock"
    mine = f"{os.getpid()} {os.uname().nodename}\n"
    for _ in range(2):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                pid_text, host = (path.read_text().split() + ["", ""])[:2]
                pid = int(pid_text)
            except (OSError, ValueError):
                pid, host = -1, ""
            if host and host != os.uname().nodename:
                raise FolderInUse(
                    f"{folder}: in use by {what} on host {host} (pid {pid}; lock {path}); remove the lock if that run "
                    "is gone, or give another folder"
                ) from None
            if pid > 0 and _alive(pid):
                raise FolderInUse(
                    f"{folder}: in use by {what} pid {pid} (lock {path}); wait for it to finish or give another folder"
                ) from None
            with contextlib.suppress(FileNotFoundError):  # a dead holder's lock: taken over
                path.unlink()
            continue
        with os.fdopen(fd, "w") as handle:
            handle.write(mine)
        break
    else:
        raise FolderInUse(f"{folder}: could not take the lock {path} (another run took it at the same time)")
    try:
        yield path
    finally:
        with contextlib.suppress(OSError):
            if path.read_text() == mine:
                path.unlink()
