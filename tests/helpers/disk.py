"""A full (or read-only) disk, injected: every ``os.fsync`` after the first few fails with an OSError
(``icpflow.core.atomic`` fsyncs each file it writes and its folder)."""

import errno
import os
from pathlib import Path


def fail_fsync_after(monkeypatch, calls: int, code: int = errno.ENOSPC, place: Path | None = None) -> None:
    """Every fsync after the first ``calls`` fails with ``code`` (ENOSPC: a full disk); with ``place``, only the
    fsyncs of files and folders under it count and fail (other places stay writable)."""
    real, count = os.fsync, [0]

    def fsync(fd):
        if place is None or Path(os.readlink(f"/proc/self/fd/{fd}")).is_relative_to(place):
            count[0] += 1
            if count[0] > calls:
                raise OSError(code, os.strerror(code))
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
