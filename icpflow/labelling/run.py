"""Label shards with the teacher: local processes or Ray, resumable, failures recorded, Ctrl-C safe."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import sys
import threading
import time
from collections import deque
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import yaml

from icpflow.atomic import write_text_atomic
from icpflow.datasets.base import sample_id_or_index
from icpflow.frames import FramePairError
from icpflow.shards.reader import read_shard_samples
from icpflow.shards.schema import shard_name
from icpflow.shards.verify import ShardError, verify_shard
from icpflow.shards.writer import write_failures, write_index, write_shard

#: failure reason of a sample during which a worker process died
DIED = (
    "WorkerDied: the worker process died labelling this sample (killed, e.g. out of memory, or crashed in native code)"
)
#: a sample that killed its worker this many times in a row is not tried again (``overwrite=true`` does)
MAX_DEATHS = 2


def config_hash(config_yaml: str) -> str:
    """Short stable hash of the labeller config text."""
    return hashlib.sha256(config_yaml.encode()).hexdigest()[:16]


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity: SLURM and cgroup allocations), else ``os.cpu_count()``."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


class LabelError(RuntimeError):
    """A labelling run cannot start or go on (config mismatch, bad option, a worker died outside a sample).
    The message is one line."""


class Terminated(KeyboardInterrupt):
    """SIGTERM reached the main process: the run stops as on Ctrl-C (a KeyboardInterrupt, so no sample's
    ``except Exception`` swallows it)."""


def raise_terminated(signum, frame) -> None:
    """SIGTERM handler of the main process (see :class:`Terminated`)."""
    raise Terminated()


@dataclass
class LabelJob:
    """Everything a worker needs to label a shard (picklable): dataset, teacher config and output settings."""

    dataset: object
    teacher_cfg: object
    out_dir: Path
    config_yaml: str
    horizon: int = 1
    tracker: bool = False
    compression: str | None = None
    hash: str = field(init=False)

    def __post_init__(self):
        self.out_dir = Path(self.out_dir)
        self.hash = config_hash(self.config_yaml)


@contextmanager
def thread_limit(threads: int, torch_too: bool = False):
    """Run the block with numba, BLAS/OpenMP and (``torch_too``) torch on at most ``threads`` threads each;
    the previous numba and torch settings come back afterwards."""
    import numba
    from threadpoolctl import threadpool_limits

    numba_before = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    torch_before = None
    if torch_too:
        import torch

        torch_before = torch.get_num_threads()
        torch.set_num_threads(threads)
    try:
        with threadpool_limits(threads):
            yield
    finally:
        numba.set_num_threads(numba_before)
        if torch_before is not None:
            torch.set_num_threads(torch_before)


def _sample(dataset, teacher, pair, index: int, horizon: int, tracker: bool) -> dict:
    """One labelled sample of ``pair`` as written to a shard (see ``icpflow.shards.schema``)."""
    if tracker and horizon > 1:
        from icpflow.teacher.tracker import sample_tracker_flow

        result = sample_tracker_flow(teacher, dataset, index, horizon, pair)
        flow, confidence, ego = result.flow, result.confidence, result.ego_k_from_0
        ground0 = pair.ground0 if pair.ground0 is not None else np.zeros(len(pair.pc0), bool)
        ground1 = pair.ground1 if pair.ground1 is not None else np.zeros(len(pair.pc1), bool)
        cluster = np.full(len(pair.pc0), -1, np.int32)  # chains span several clusterings: no single id
    else:
        result = teacher(
            pair.pc0,
            pair.pc1,
            ego1_from_ego0=pair.ego1_from_ego0,
            ground0=pair.ground0,
            ground1=pair.ground1,
            time0=pair.time0,
            time1=pair.time1,
            gap=horizon,
            dt=pair.dt,
        )
        flow, confidence, cluster = result.flow, result.confidence, result.labels0
        ground0, ground1, ego = result.ground0, result.ground1, result.ego1_from_ego0
    return {
        "pc0": pair.pc0,
        "pc1": pair.pc1,
        "ground0": np.asarray(ground0, bool),
        "ground1": np.asarray(ground1, bool),
        "ego1_from_ego0": np.asarray(ego, np.float64),
        "flow": np.asarray(flow, np.float32),
        "confidence": np.asarray(confidence, np.float32),
        "cluster": np.asarray(cluster, np.int32),
        "gt_flow": pair.flow,
        "gt_flow_valid": pair.flow_valid,
        "gt_classes": pair.classes,
        "gt_dynamic": pair.dynamic,
        "attrs": {
            "sample_id": pair.sample_id or sample_id_or_index(dataset, index),
            "log_id": pair.log_id,
            "index": index,
            "timestamp0_ns": -1 if pair.timestamp0_ns is None else int(pair.timestamp0_ns),
            "timestamp1_ns": -1 if pair.timestamp1_ns is None else int(pair.timestamp1_ns),
            "dt": float(pair.dt),
        },
    }


def label_shard(
    job: LabelJob,
    shard: int,
    indices: list[int],
    ticks=None,
    threads: int | None = None,
    lost: dict | None = None,
    previous: dict | None = None,
) -> dict:
    """Label ``indices``, write shard ``shard`` and its record; a sample that raises is recorded, not fatal.

    ``ticks``: optional queue (or callable) told ``(index, False)`` when a sample starts and ``(index, True)`` when
    it is finished. ``threads``: run the teacher on at most this many threads (numba, BLAS, hdbscan's n_jobs;
    the labels do not change). ``lost``: ``{index: failure record}`` of samples not to run (they killed a worker);
    they are recorded as failures. ``previous``: the record of a valid earlier shard of these indices whose
    labelled samples are copied from its file (only its failed samples are labelled again).

    The record (``shard_XXXXXX.h5.json``, with the reader's sample ids of ``indices``) is written here, so a
    finished shard is kept even if the main process dies. Returns ``{"shard", "file", "samples": [{"sample_id",
    "index", "n0", "n1"}], "failures": [...], "reused", "seconds"}`` (``reused``: samples copied from
    ``previous``); a failure's ``sample_id`` is the pair's id, or the reader's ``sample_id(index)`` when the pair
    could not be read.
    """
    from icpflow.teacher import ICPFlow

    start = time.perf_counter()
    threads = threads or available_cores()
    cfg = job.teacher_cfg
    teacher = ICPFlow(cfg.replace(**{"clustering.n_jobs": min(cfg.clustering.n_jobs, threads)}))
    tell = (ticks if callable(ticks) else ticks.put) if ticks is not None else (lambda message: None)
    lost = lost or {}
    name = shard_name(shard)
    kept = {}
    if previous is not None:
        kept = {int(sample["attrs"]["index"]): sample for sample in read_shard_samples(job.out_dir / name)}
    samples, failures = [], []
    with thread_limit(threads, torch_too=cfg.icp.backend == "torch"):
        for index in indices:
            if index in kept:
                samples.append(kept[index])
                continue
            if index in lost:
                failures.append(lost[index])
                tell((index, True))
                continue
            tell((index, False))
            pair = None
            try:
                pair = job.dataset.pair(index, horizon=job.horizon)
                sample = _sample(job.dataset, teacher, pair, index, job.horizon, job.tracker)
            except Exception as error:  # any reader or teacher failure skips this sample only
                sample_id = (
                    pair.sample_id if pair is not None and pair.sample_id else sample_id_or_index(job.dataset, index)
                )
                source = getattr(error, "filename", None) or sample_id
                if isinstance(error, FramePairError) and pair is None:  # a reader's: its message starts with the file
                    source = str(error).split(": ", 1)[0]
                reason = f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"
                failures.append({"index": index, "sample_id": sample_id, "file": str(source), "reason": reason})
            else:
                samples.append(sample)
            tell((index, True))
    write_shard(job.out_dir / name, samples, job.config_yaml, job.hash, job.compression)
    records = [
        {
            "sample_id": str(sample["attrs"]["sample_id"]),
            "index": int(sample["attrs"]["index"]),
            "n0": int(sample["pc0"].shape[0]),
            "n1": int(sample["pc1"].shape[0]),
        }
        for sample in samples
    ]
    result = {
        "shard": shard,
        "file": name,
        "samples": records,
        "failures": failures,
        "reused": len(kept),
        "seconds": time.perf_counter() - start,
    }
    write_text_atomic(
        _state_path(job.out_dir, shard),
        json.dumps(
            {**result, "config_hash": job.hash, "ids": [sample_id_or_index(job.dataset, i) for i in indices]},
            sort_keys=True,
        ),
    )
    return result


def _state_path(out_dir: Path, shard: int) -> Path:
    return out_dir / f"{shard_name(shard)}.json"


def _record(job: LabelJob, shard: int) -> dict | None:
    try:
        record = json.loads(_state_path(job.out_dir, shard).read_text())
    except (OSError, ValueError):
        return None
    return record if record.get("config_hash") == job.hash else None


def _done(job: LabelJob, shard: int, indices: list[int], ids: list[str]) -> dict | None:
    """The stored result of a complete, valid shard of this config covering ``indices`` whose reader sample ids
    were ``ids`` when it was labelled, or None (its failed samples may still be worth retrying: :func:`_retried`)."""
    record = _record(job, shard)
    if record is None or record.get("ids") != ids:
        return None
    covered = sorted([r["index"] for r in record["samples"]] + [f["index"] for f in record["failures"]])
    if covered != indices:
        return None
    try:
        verify_shard(job.out_dir / record["file"], job.hash, len(record["samples"]))
    except ShardError:
        return None
    return record


def _retried(record: dict) -> tuple[list[int], dict]:
    """The failed samples of a shard record to label again, and ``{index: failure}`` of those that are not: the
    samples that killed their worker ``MAX_DEATHS`` times in a row."""
    lost = {f["index"]: f for f in record["failures"] if f.get("deaths", 0) >= MAX_DEATHS}
    return [f["index"] for f in record["failures"] if f["index"] not in lost], lost


def _died(dataset, index: int, previous: dict | None) -> dict:
    """The failure record of sample ``index`` that killed its worker (counting deaths in a row across runs)."""
    before = next((f for f in (previous or {}).get("failures", ()) if f["index"] == index), {})
    deaths = before.get("deaths", 0) + 1
    reason = DIED if deaths < MAX_DEATHS else f"{DIED}; {deaths} times in a row, not tried again (overwrite=true does)"
    sample_id = sample_id_or_index(dataset, index)
    return {"index": index, "sample_id": sample_id, "file": sample_id, "reason": reason, "deaths": deaths}


def _flat(node, prefix: str = "") -> dict:
    if not isinstance(node, dict):
        return {prefix: node}
    return {k: v for key, value in node.items() for k, v in _flat(value, f"{prefix}{key}.").items()}


def config_changes(old_yaml: str, new_yaml: str, shown: int = 3) -> str:
    """``key: old -> new, ...`` for the first ``shown`` settings that differ between two labeller configs."""
    try:
        old, new = _flat(yaml.safe_load(old_yaml)), _flat(yaml.safe_load(new_yaml))
    except yaml.YAMLError:
        return "unreadable config.yaml"
    keys = sorted(key for key in old.keys() | new.keys() if old.get(key) != new.get(key))
    text = ", ".join(f"{key.rstrip('.')}: {old.get(key)} -> {new.get(key)}" for key in keys[:shown])
    return text + (f" and {len(keys) - shown} more" if len(keys) > shown else "")


def _remove_temporaries(out_dir: Path, shard: int) -> None:
    name = shard_name(shard)
    for stale in [*out_dir.glob(f"{name}.tmp-*"), *out_dir.glob(f"{name}.json.tmp-*")]:
        stale.unlink(missing_ok=True)


def prepare(job: LabelJob, plan: list[tuple[int, list[int]]], overwrite: bool) -> None:
    """Create ``out_dir``; refuse one labelled by another config unless ``overwrite``.

    With ``overwrite``, shards of another config and this plan's shards are removed (other jobs' shards of the
    same config, e.g. SLURM array tasks, are left alone). Leftover temporary files of this plan's shards (from a
    killed run) are removed.
    """
    job.out_dir.mkdir(parents=True, exist_ok=True)
    marker = job.out_dir / "config.yaml"
    if marker.is_file() and config_hash(marker.read_text()) != job.hash:
        if not overwrite:
            raise LabelError(
                f"{job.out_dir}: labelled with another config (hash {config_hash(marker.read_text())}, "
                f"now {job.hash}: {config_changes(marker.read_text(), job.config_yaml)}); pass "
                f"overwrite=true to relabel, or choose another out_dir"
            )
        for state in job.out_dir.glob("shard_*.h5.json"):
            if json.loads(state.read_text()).get("config_hash") != job.hash:
                state.unlink()
                (job.out_dir / state.name[: -len(".json")]).unlink(missing_ok=True)
    for shard, _ in plan:
        _remove_temporaries(job.out_dir, shard)
        if overwrite:
            _state_path(job.out_dir, shard).unlink(missing_ok=True)
            (job.out_dir / shard_name(shard)).unlink(missing_ok=True)
    write_text_atomic(marker, job.config_yaml)


def write_manifests(job: LabelJob) -> list[dict]:
    """``index.json`` and ``failures.jsonl`` from every finished shard of this config in ``out_dir``.

    Reads all shard records, so concurrent jobs (one per SLURM array task) each leave a complete index behind
    when they finish last. Returns the failures.
    """
    records = []
    for state in sorted(job.out_dir.glob("shard_*.h5.json")):
        record = json.loads(state.read_text())
        if record.get("config_hash") == job.hash:
            records.append(record)
    write_index(
        job.out_dir / "index.json",
        {
            "config_hash": job.hash,
            "shards": [{"file": r["file"], "samples": r["samples"]} for r in records if r["samples"]],
        },
    )
    failures = [f for r in records for f in r["failures"]]
    write_failures(job.out_dir / "failures.jsonl", failures)
    return failures


def _end_helpers() -> None:
    """Terminate the child processes a worker's libraries started (hdbscan's joblib pool idles for minutes and
    would otherwise keep the worker, and so the pool, from exiting)."""
    import multiprocessing

    for child in multiprocessing.active_children():
        child.terminate()


def exit_with_parent() -> None:
    """End this process (SIGKILL) as soon as the process that started it ends, whatever ended that one (SIGKILL,
    SIGTERM, the out-of-memory killer): ``prctl(PR_SET_PDEATHSIG)`` on Linux, elsewhere a daemon thread that
    checks the parent's pid every 0.5 s. For the processes of a run (workers, their queue manager)."""
    import multiprocessing

    parent = multiprocessing.parent_process()
    parent_pid = parent.pid if parent is not None else os.getppid()
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # 1 = PR_SET_PDEATHSIG
    else:

        def watch():
            while os.getppid() == parent_pid:
                time.sleep(0.5)
            os.kill(os.getpid(), signal.SIGKILL)

        threading.Thread(target=watch, daemon=True).start()
    if os.getppid() != parent_pid:  # the parent ended before the watch began
        os.kill(os.getpid(), signal.SIGKILL)


def _worker_init() -> None:
    """A worker leaves Ctrl-C to the main process, which ends it (a terminal sends SIGINT to the whole group),
    and never outlives the main process."""
    from multiprocessing.util import Finalize

    from icpflow.console import worker_logging

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    worker_logging()  # warnings on a line of their own, not inside the main process's progress bar
    exit_with_parent()
    Finalize(None, _end_helpers, exitpriority=100)


def _end_now(executor: ProcessPoolExecutor) -> None:
    """Terminate a one-process executor's worker even mid-shard (no public API for this before Python 3.14)."""
    for process in list((executor._processes or {}).values()):
        process.terminate()
    executor.shutdown(wait=True, cancel_futures=True)


def _pool_results(job, todo, workers, threads, tick):
    """Shard results from ``workers`` spawned processes, as they finish; ``tick(n)`` per finished sample.

    ``todo``: ``[(shard, indices, lost, previous)]`` (see :func:`label_shard`). Each process is its own one-worker
    executor, so a process that dies (killed, out of memory, a crash in native code) is known to have died in its
    own shard, at the sample it had started: that sample is recorded as a failure, the shard is labelled again
    without it in a fresh process, and the other shards go on. A process that dies outside a sample stops the run
    (LabelError). On exit (done, Ctrl-C, error) every process is ended; if the main process itself is killed, they
    end with it (:func:`exit_with_parent`).
    """
    from multiprocessing.managers import SyncManager

    context = get_context("spawn")
    queue = deque(todo)
    running, idle = {}, []
    started, finished = set(), set()
    manager = SyncManager(ctx=context)
    manager.start(exit_with_parent)
    with manager:
        ticks = manager.Queue()
        try:
            while queue or running:
                while queue and len(running) < workers:
                    if not idle:
                        idle.append(ProcessPoolExecutor(1, mp_context=context, initializer=_worker_init))
                    executor = idle.pop()
                    shard, indices, lost, previous = queue.popleft()
                    future = executor.submit(label_shard, job, shard, indices, ticks, threads, lost, previous)
                    running[future] = (executor, shard, indices, lost, previous)
                done, _ = wait(running, timeout=0.5, return_when=FIRST_COMPLETED)
                while not ticks.empty():  # a worker's messages are queued before it moves on, so before it dies
                    index, ended = ticks.get()
                    (finished if ended else started).add(index)
                    tick(int(ended))
                for future in done:
                    executor, shard, indices, lost, previous = running.pop(future)
                    crashed = [i for i in indices if i in started and i not in finished]
                    counted = sum(i in finished for i in indices)
                    started.difference_update(indices)
                    finished.difference_update(indices)
                    if not isinstance(future.exception(), BrokenProcessPool):
                        idle.append(executor)  # its process lives on (also after an error such as a full disk)
                        yield future.result()
                        continue
                    executor.shutdown(wait=True)
                    _remove_temporaries(job.out_dir, shard)
                    if not crashed:
                        raise LabelError(
                            f"a worker process died outside any sample of {shard_name(shard)} "
                            f"(killed, or a crash loading the teacher); complete shards are kept"
                        )
                    tick(-counted)  # the retry counts them again
                    lost = {**lost, crashed[0]: _died(job.dataset, crashed[0], previous)}
                    queue.appendleft((shard, indices, lost, previous))
        finally:
            for executor, shard, *_ in running.values():
                _end_now(executor)
                _remove_temporaries(job.out_dir, shard)
            for executor in idle:
                executor.shutdown(wait=True)


def _ray_results(job, todo, address, workers, tick):
    """Shard results from Ray tasks (one per shard, 1 CPU and 1 thread each), as they finish; ticks per shard."""
    import ray

    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    remote = ray.remote(num_cpus=1)(label_shard)
    pending = [remote.remote(job, shard, indices, None, 1, lost, previous) for shard, indices, lost, previous in todo]
    try:
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            result = ray.get(ready[0])
            tick(len(result["samples"]) + len(result["failures"]) - result["reused"])
            yield result
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)


def _in_process_results(job, todo, threads, tick):
    """Shard results labelled one after the other in this process."""
    for shard, indices, lost, previous in todo:
        yield label_shard(job, shard, indices, lambda message: tick(int(message[1])), threads, lost, previous)


def run_labelling(
    job: LabelJob,
    plan: list[tuple[int, list[int]]],
    workers: int = 1,
    runner: str = "local",
    ray_address: str | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """Label every sample of ``plan`` not already labelled; then write ``index.json`` and ``failures.jsonl``.

    Each finished shard is recorded at once (``shard_XXXXXX.h5.json``, with the reader's sample ids of its
    indices), so a killed run loses only shards in flight. A rerun labels the samples that failed before (a
    fixed input file, a transient death) and keeps the others of their shard, except samples that killed their
    worker ``MAX_DEATHS`` times in a row. ``workers`` local processes share the available cores (each runs the
    teacher on ``cores // workers`` threads). Returns ``{"done", "skipped", "failed", "seconds_per_sample",
    "seconds", "failures"}``: samples labelled now, samples labelled by an earlier run, failed samples of this
    plan, mean reader + teacher seconds per labelled sample in a worker, wall-clock seconds. ``index.json`` is
    written on every exit (also on Ctrl-C or an error), from the shards then on disk.
    """
    from icpflow.console import Progress

    if runner not in ("local", "ray"):
        raise LabelError(f"runner must be local or ray, got {runner!r}")
    start = time.perf_counter()
    prepare(job, plan, overwrite)
    results, todo, skipped, total = {}, [], 0, 0
    for shard, indices in plan:
        record = _done(job, shard, indices, [sample_id_or_index(job.dataset, i) for i in indices])
        if record is None:
            todo.append((shard, indices, {}, None))
            total += len(indices)
            continue
        retry, lost = _retried(record)
        skipped += len(record["samples"])
        if retry:
            todo.append((shard, indices, lost, record))
            total += len(retry) + len(lost)
        else:
            results[shard] = record
    seconds, done = 0.0, 0
    bar = Progress(
        total=total,
        unit=" samples",
        disable=not progress,
        dynamic_ncols=True,
        desc="labelling",
        bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}, {rate_noinv_fmt}]",
    )
    parallel = max(1, min(workers, len(todo)))
    if runner == "ray":
        stream = _ray_results(job, todo, ray_address, workers, bar.update)
    elif (
        workers > 1 and todo
    ):  # worker processes even for one shard: a sample that kills its process must not end the run
        stream = _pool_results(job, todo, parallel, max(1, available_cores() // parallel), bar.update)
    else:
        stream = _in_process_results(job, todo, available_cores(), bar.update)
    stopped = True
    try:
        for result in stream:
            results[result["shard"]] = result
            seconds += result["seconds"]
            done += len(result["samples"]) - result["reused"]
        stopped = False
    finally:
        stream.close()
        bar.close()
        try:
            write_manifests(job)
        except OSError:
            if not stopped:
                raise  # else (e.g. the disk is full) the error that stopped the run is the one to report
    failures = [f for shard in sorted(results) for f in results[shard]["failures"]]
    return {
        "done": done,
        "skipped": skipped,
        "failed": len(failures),
        "seconds_per_sample": seconds / done if done else 0.0,
        "seconds": time.perf_counter() - start,
        "failures": failures,
    }
