"""Readers that the tests name as ``dataset.reader._target_`` in label.py and eval.py runs of their own (importable
in those processes: ``tests/`` is on their Python path, helpers.labelling.TESTS_ENV): the synthetic world with a
fault of some kind."""

import errno
import multiprocessing
import os
import signal
import time
from pathlib import Path

from icpflow.core.frame_pair import FramePairError
from icpflow.datasets.synthetic.reader import SyntheticDataset


class DiskFullSynthetic(SyntheticDataset):
    """The small world in a label.py run whose disk fills up while the workers label: from the moment this reader is
    built in the main process, which writes the shards, every fsync of shard 0's files fails with ENOSPC (the small
    index and records still fit)."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        real = os.fsync

        def fsync(fd):
            if os.readlink(f"/proc/self/fd/{fd}").rsplit("/", 1)[-1].startswith("shard_000000.h5"):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            real(fd)

        os.fsync = fsync  # in the main process of this label.py run only


def idle_helper(ready: str) -> None:
    """A library's worker process: ignores Ctrl-C (its parent handles it), says it is up, waits ten minutes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    Path(ready).touch()
    time.sleep(600)


class StallAfterFirst(SyntheticDataset):
    """The small synthetic world whose second sample takes a minute to read; ``marker`` appears when it starts.
    Before it stalls it starts a helper process that would run for ten minutes, as a library's worker pool does
    (hdbscan's loky workers did, and once outlived a terminated eval.py)."""

    def __init__(self, marker, **kwargs):
        super().__init__(**kwargs)
        self.marker = Path(marker)

    def pair(self, index, horizon=1):
        if index >= 1:
            ready = self.marker.with_name("helper-ready")
            multiprocessing.get_context("spawn").Process(target=idle_helper, args=(str(ready),)).start()
            while not ready.exists():  # up and ignoring Ctrl-C before the test signals the group
                time.sleep(0.05)
            self.marker.touch()
            time.sleep(60)
        return super().pair(index, horizon)


class FlakySynthetic(SyntheticDataset):
    """The small synthetic world where the reader fails on sample 1 and sample 3 reaches the teacher with an empty
    pc0 but a full ground mask (the teacher rejects it)."""

    def pair(self, index, horizon=1):
        if index == 1:
            raise FramePairError("/data/log/000001.bin: pc0 must have shape (N, 3), got (7,)")
        pair = super().pair(index, horizon)
        if index == 3:
            pair.pc0 = pair.pc0[:0]
        return pair
