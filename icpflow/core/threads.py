"""The CPU a step runs on: how many cores this process has (:func:`available_cores`), what the CPU says of itself
(:func:`cpu_fields`, Linux), and a limit on the thread pools of numba, BLAS, OpenMP and torch for a block of work
(:func:`thread_limit`).

A labelling worker runs the teacher on its share of the cores; a stream that overlaps its network with its own steps
(``fastflow3d.inference.stream``) runs those steps on one thread, so that their thread pools do not spin on the core
the network runs on (on 2 cores that makes a frame quicker, plain and refined: BENCHMARKS.md, "Student latency and the
stream").
"""

from __future__ import annotations

import os
from contextlib import contextmanager
from pathlib import Path


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity: SLURM and cgroup allocations), else ``os.cpu_count()``."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def cpu_fields(cpuinfo: str | None = None) -> dict[str, str]:
    """The first processor's fields of ``/proc/cpuinfo`` (``cpuinfo``: its text, read when None), e.g. ``model name``,
    ``cpu family``, ``flags`` (x86) or ``Features`` (Arm); {} where there is no such file (not Linux)."""
    try:
        text = Path("/proc/cpuinfo").read_text() if cpuinfo is None else cpuinfo
    except OSError:
        return {}
    fields = {}
    for line in text.split("\n\n", 1)[0].splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    return fields


@contextmanager
def thread_limit(threads: int, torch_too: bool = False, controller=None):
    """Run the block with numba, BLAS/OpenMP and (``torch_too``) torch on at most ``threads`` threads each; the
    previous settings come back afterwards. numba's and torch's settings (OpenMP's too, where torch uses it) are the
    calling thread's own: another thread's work keeps its threads. ``controller``: a
    ``threadpoolctl.ThreadpoolController`` made once by a caller that enters the limit often (finding the loaded
    libraries anew takes about 2 ms)."""
    import numba
    from threadpoolctl import ThreadpoolController

    numba_before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    torch_before = None
    if torch_too:
        import torch

        torch_before = torch.get_num_threads()
        torch.set_num_threads(threads)
    try:
        with (controller or ThreadpoolController()).limit(limits=threads):
            yield
    finally:
        numba.set_num_threads(numba_before)
        if torch_before is not None:
            torch.set_num_threads(torch_before)
