"""Where samples are labelled: in this process, on a pool of local worker processes (pebble), or as Ray tasks.

Each executor takes a job and sample indices and yields :func:`icpflow.labelling.sample.label_sample`'s outcome of
each sample as it finishes (in any order), or ``{"index", "seconds": 0.0, "died": True}`` for a sample whose worker
process died (killed, out of memory, a crash in native code): an ordinary task error, the other samples go on.
Closing the generator (done, Ctrl-C, SIGTERM, an error in the caller) ends every process it started.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, wait
from concurrent.futures.process import BrokenProcessPool
from multiprocessing import get_context

from icpflow.core.errors_and_signals import signals_held
from icpflow.labelling.job import LabelError, LabelJob
from icpflow.labelling.sample import label_sample

#: seconds between a worker's checks that the main process still lives
PARENT_CHECK_S = 0.2


def in_process(job: LabelJob, indices: list[int], threads: int) -> Iterator[dict]:
    """The samples labelled one after the other in this process."""
    for index in indices:
        yield label_sample(job, index, threads)


def _end_helpers() -> None:
    """Terminate the child processes a worker's libraries started (hdbscan's joblib pool idles for minutes and
    would otherwise outlive the worker)."""
    import multiprocessing

    for child in multiprocessing.active_children():
        child.terminate()


def _end_with_parent() -> None:
    """End this worker (its helpers, then itself with SIGKILL) as soon as the main process is gone, whatever ended
    it (SIGKILL, the out-of-memory killer): a daemon thread compares the parent pid every ``PARENT_CHECK_S``."""
    import multiprocessing

    parent = multiprocessing.parent_process()
    parent_pid = parent.pid if parent is not None else os.getppid()

    def watch():
        while os.getppid() == parent_pid:
            time.sleep(PARENT_CHECK_S)
        _end_helpers()
        os.kill(os.getpid(), getattr(signal, "SIGKILL", signal.SIGTERM))  # Windows has no SIGKILL; its SIGTERM kills

    threading.Thread(target=watch, name="end-with-parent", daemon=True).start()


def _start_worker() -> None:
    """Initialiser of a pool worker: it leaves Ctrl-C to the main process (which ends the pool), never outlives the
    main process, and ends its libraries' helper processes when it exits."""
    from multiprocessing.util import Finalize

    from icpflow.core.console import worker_logging

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    worker_logging()  # warnings on a line of their own, not inside the main process's progress bar
    _end_with_parent()
    Finalize(None, _end_helpers, exitpriority=100)


def local_pool(job: LabelJob, indices: list[int], workers: int, threads: int) -> Iterator[dict]:
    """The samples labelled by ``workers`` spawned processes (a pebble ``ProcessPool``), each teacher on ``threads``
    threads. A worker that dies fails its sample only (pebble replaces it); one that dies outside a sample (e.g. while
    starting) breaks the pool and stops the run (LabelError). At most two samples per worker are queued ahead."""
    from pebble import ProcessExpired, ProcessPool

    pool = ProcessPool(max_workers=workers, initializer=_start_worker, context=get_context("spawn"))
    waiting, running = deque(indices), {}
    try:
        while waiting or running:
            while waiting and len(running) < 2 * workers:
                index = waiting.popleft()
                with signals_held():  # the pool spawns its workers here, in this thread, on its first task: a stop
                    # between a worker's start and the write of its channel would leave it failing to read it
                    running[pool.schedule(label_sample, (job, index, threads))] = index
            done, _ = wait(running, timeout=0.5, return_when=FIRST_COMPLETED)
            for future in done:
                index = running.pop(future)
                try:
                    outcome = future.result()
                except ProcessExpired:
                    outcome = {"index": index, "seconds": 0.0, "died": True}
                except BrokenProcessPool:
                    raise LabelError(
                        "a worker process died outside any sample (killed, or a crash loading the teacher); "
                        "complete shards are kept"
                    ) from None
                yield outcome
    finally:
        pool.stop()
        pool.join()
        # a worker the pool was still spawning when it stopped may outlive it and, once this process is gone, fail to
        # unpickle its channel with a traceback of its own: a SIGTERM before its start is done ends it silently
        _end_helpers()


def ray_tasks(job: LabelJob, indices: list[int], address: str | None, workers: int) -> Iterator[dict]:
    """The samples labelled as Ray tasks (1 CPU and 1 thread each, never retried: a crashed worker fails its sample)
    on the cluster at ``address``, or on a local one of ``workers`` CPUs."""
    import ray

    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    remote = ray.remote(num_cpus=1, max_retries=0)(label_sample)
    window = 2 * max(workers, int(ray.cluster_resources().get("CPU", 1)))  # samples in flight
    waiting, pending = deque(indices), {}
    try:
        while waiting or pending:
            while waiting and len(pending) < window:
                index = waiting.popleft()
                pending[remote.remote(job, index, 1)] = index
            ready, _ = ray.wait(list(pending), num_returns=1)
            index = pending.pop(ready[0])
            try:
                outcome = ray.get(ready[0])
            except ray.exceptions.WorkerCrashedError:
                outcome = {"index": index, "seconds": 0.0, "died": True}
            yield outcome
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
