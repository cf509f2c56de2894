"""A full disk, injected: every ``os.fsync`` after the first few fails with ENOSPC (``icpflow.atomic`` fsyncs each
file it writes and its folder)."""

import errno
import os


def fail_fsync_after(monkeypatch, calls: int) -> None:
    """Every fsync after the first ``calls`` fails with ENOSPC, as on a full disk."""
    real, count = os.fsync, [0]

    def fsync(fd):
        count[0] += 1
        if count[0] > calls:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd)

    monkeypatch.setattr(os, "fsync", fsync)
