"""The teacher's numba kernels, compiled once per environment, with a line saying so.

numba compiles each ``@numba.njit(cache=True)`` kernel of the teacher (the modules ``KERNEL_MODULES``) on its
first call and caches the machine code on disk (in ``__pycache__`` next to the sources, or under
``NUMBA_CACHE_DIR``); later processes load it in well under a second. Compiling costs about 45 s on 2 idle cores
(minutes on a busy machine), once per environment and source version. ``setup.sh`` pays it
(``python -m icpflow.teacher.warmup``); ``label.py`` and ``eval.py`` call :func:`ensure_compiled` before their first
pair, so a cold cache is filled once, in the main process and with a message, instead of by every worker inside its
first sample behind a progress bar at 0; a student ``Predictor`` calls :func:`prepare_kernels` (once per process) on
its first pair, never from its constructor.

numba keys a kernel's cached code by its own source file only, and a kernel that calls another module's kernel (the
refinement's batch ICP calls ``icp`` and ``neighbours``) caches the callee's code with its own: after a change to the
callee's file alone (an edit, a ``git pull`` of an editable install) the caller would run the old callee, silently.
So the cache carries a stamp of the
sources it was compiled from (:data:`SOURCES_STAMP`, :func:`sources_fingerprint`); where it differs, every kernel is
cold, and :func:`ensure_compiled` empties the whole cache before it compiles.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import importlib.util
import sys
import time
from pathlib import Path

from icpflow.core.atomic import write_text_atomic
from icpflow.core.errors_and_signals import raise_swallowed_stop
from icpflow.core.stops import raise_stop_behind

#: the modules whose numba kernels the teacher calls on the CPU (the ground's also the Predictor and the stream; the
#: bird's-eye-view cells only the student's refinement; the plane normals also the odometry)
KERNEL_MODULES = (
    "icpflow.scans.neighbours",
    "icpflow.teacher.registration.icp",
    "icpflow.teacher.histogram",
    "icpflow.teacher.registration.cpu",
    "icpflow.teacher.hdbscan_labels",
    "icpflow.scans.ground",
    "icpflow.scans.bev",
    "icpflow.scans.normals",
)
#: the file, beside the cached machine code, that holds :func:`sources_fingerprint` of the sources it was compiled from
SOURCES_STAMP = "kernel-sources.sha256"


def kernels() -> dict:
    """``{"module.function": numba dispatcher}`` of every jitted function in ``KERNEL_MODULES`` (the module's path
    below ``icpflow``: ``scans.neighbours.nearest``)."""
    from numba.core.dispatcher import Dispatcher

    found = {}
    for name in KERNEL_MODULES:
        module = importlib.import_module(name)
        for attribute, value in vars(module).items():
            if isinstance(value, Dispatcher) and value.__module__ == name:
                found[f"{name.removeprefix('icpflow.')}.{attribute}"] = value
    return found


def _cached(dispatcher) -> bool:
    """True if numba's on-disk cache holds machine code of ``dispatcher`` for its current source on this CPU."""
    try:
        index = dispatcher._cache._cache_file._load_index()  # {} when the source changed since it was written
        target = dispatcher.targetctx.codegen().magic_tuple()
    except Exception as error:  # no cache (cache=False, unwritable) or another numba layout: treat as cold
        raise_stop_behind(error)
        return False
    return any(key[1] == target for key in index)


def sources_fingerprint() -> str:
    """The sha256 (hex) of the source files of ``KERNEL_MODULES``, in order (module docstring)."""
    digest = hashlib.sha256()
    for name in KERNEL_MODULES:
        digest.update(name.encode())
        digest.update(Path(importlib.util.find_spec(name).origin).read_bytes())
    return digest.hexdigest()


def _cache_folder() -> Path | None:
    """The folder of the first kernel's cached machine code (None where numba has none)."""
    dispatcher = next(iter(kernels().values()))
    try:
        return Path(dispatcher._cache._cache_path)
    except Exception as error:
        raise_stop_behind(error)
        return None


def stale_cache() -> bool:
    """True where the cache's :data:`SOURCES_STAMP` is missing or names other sources than these (module
    docstring): none of its machine code may be used."""
    folder = _cache_folder()
    if folder is None:
        return False
    try:
        return (folder / SOURCES_STAMP).read_text(encoding="utf-8").strip() != sources_fingerprint()
    except OSError:
        return True


def cold_kernels(stale: bool | None = None) -> list[str]:
    """Names of the kernels (see :func:`kernels`) with no usable cached machine code (none cached for these
    sources, or a stale cache: :func:`stale_cache`, or ``stale`` where the caller has it): each compiles on its first
    call."""
    found = kernels()
    if stale_cache() if stale is None else stale:
        return list(found)
    return [name for name, dispatcher in found.items() if not _cached(dispatcher)]


def cache_location() -> str:
    """Where the kernels' machine code is cached (a folder)."""
    folder = _cache_folder()
    return "numba's cache" if folder is None else str(folder)


def compile_kernels() -> None:
    """Call every kernel with the types a labelling run uses: the teacher (av2 preset: ground removal, histogram vote,
    ICP both ways, de-skew) on a small synthetic pair with per-point capture times; then the kernels of these
    modules that only the student's refinement calls (``fastflow3d.inference.refine``: the coarse-to-fine batch ICP,
    the exact nearest distances and the bird's-eye-view cells), with its types, on small clouds (else they stay
    cold, and every run after set-up would say so and compile again); and the odometry's k nearest neighbours and
    plane normals (``icpflow.scans.odometry``: the teacher runs it only without a given ego motion)."""
    import numpy as np

    from icpflow.datasets.synthetic.reader import SyntheticDataset
    from icpflow.scans.bev import in_box_cells, occupied_cells
    from icpflow.scans.neighbours import build_grid, nearest_distances
    from icpflow.scans.normals import plane_normals, smallest_axes
    from icpflow.scans.odometry import TargetPlanes
    from icpflow.teacher import ICPFlow, ICPFlowConfig
    from icpflow.teacher.registration.cpu import grid_cell, register_stages_cpu

    pair = SyntheticDataset(
        split="train", num_sequences=1, frames_per_sequence=2, beams=32, azimuth_resolution_deg=0.5
    ).pair(0)
    times0 = np.linspace(0.0, 0.1, len(pair.pc0), dtype=np.float32)
    times1 = np.linspace(0.0, 0.1, len(pair.pc1), dtype=np.float32)
    ICPFlow(ICPFlowConfig.preset("av2"))(
        pair.pc0, pair.pc1, pair.ego1_from_ego0, None, None, times0, times1, dt=pair.dt
    )
    cloud = np.random.default_rng(0).uniform(-1.0, 1.0, (64, 3))
    register_stages_cpu([cloud], [cloud + 0.1], [cloud], np.eye(4)[None], (0.5, 0.2), 5, 1e-6, yaw_only=True)
    cell = grid_cell(0.2)
    nearest_distances(cloud, cloud, build_grid(cloud, cell), cell, np.full(len(cloud), np.inf))
    TargetPlanes(cloud).nearest(cloud, 2)  # the odometry's neighbour queries (a pair's ego motion, a stream)
    plane_normals(cloud, np.zeros((len(cloud), 10), np.int64))  # its targets' normals (and a point-to-plane ICP's)
    smallest_axes(np.zeros((1, 3, 3)))
    # the refinement's objects and targets (icpflow.scans.bev), with its types: float32 points
    points = cloud.astype(np.float32)
    occupied_cells(points, np.float32(0.5), np.ones(len(points), bool))
    in_box_cells(points, cloud[:2], cloud[:2] + 1.0, 0.5)


def ensure_compiled(prefix: str = "icpflow", stream=None, eager: bool = True) -> bool:
    """Compile the kernels now if the cache lacks any, saying so on ``stream`` (stderr) before and after; returns
    True if it compiled. A warm cache costs only the check (milliseconds).

    ``eager`` False (the Predictor, which calls a few of the kernels): a cache of other sources is still emptied and
    stamped, but nothing compiles here; each kernel compiles, and is cached, on its first call (a fresh install's
    first KITTI stream: 14 s against 80 s with every kernel compiled first). Returns True where it emptied."""
    stream = stream or sys.stderr
    stale = stale_cache()
    raise_swallowed_stop()  # the kernels' first import (numba, scipy, numpy's Cython modules) may swallow a Ctrl-C
    if not eager:
        if stale:
            print(
                f"{prefix}: the numba kernels it calls compile on their first call, once for this environment",
                file=stream,
            )
            _restart_cache()
        return stale
    cold = cold_kernels(stale)
    if not cold:
        return False
    print(
        f"{prefix}: compiling the teacher's {len(cold)} numba kernels once for this environment"
        f"{' and these sources' if stale else ''} (about 1 min on 2 cores; cached in {cache_location()}) ...",
        file=stream,
        flush=True,
    )
    start = time.perf_counter()
    if stale:  # code compiled from other sources: none of it is kept (a kernel holds its callees' code)
        for dispatcher in kernels().values():
            dispatcher._cache.flush()
    compile_kernels()
    if stale:
        _stamp()
    print(f"{prefix}: kernels compiled in {time.perf_counter() - start:.0f} s", file=stream, flush=True)
    return True


@functools.cache
def prepare_kernels(prefix: str = "fastflow3d") -> bool:
    """The student side's kernel step, once per process (later calls return the first one's answer and do nothing):
    a cache compiled from other sources is emptied and stamped, with one line on stderr saying so; nothing compiles
    here, each kernel compiles (and is cached) on its first call: the few a Predictor calls rather than all of the
    teacher's. True where it emptied a cache. ``Predictor.predict`` and a stream's first scan call it; so may a
    caller who wants it done (and said) before the first pair."""
    return ensure_compiled(prefix, eager=False)


def _restart_cache() -> None:
    """Empty every kernel's cache (machine code of other sources) and stamp the cache with these sources."""
    for dispatcher in kernels().values():
        dispatcher._cache.flush()
    _stamp()


def _stamp() -> None:
    """Record these sources in the cache's :data:`SOURCES_STAMP`."""
    folder = _cache_folder()
    if folder is not None:
        write_text_atomic(folder / SOURCES_STAMP, sources_fingerprint(), make_parents=True)


def main() -> int:
    """``python -m icpflow.teacher.warmup``: fill the cache (setup.sh); say so when it was already warm."""
    if not ensure_compiled("warmup"):
        print(f"warmup: the teacher's numba kernels are already compiled ({cache_location()})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
