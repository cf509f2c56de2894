"""Label shards with the teacher: local process pool or Ray, resumable, failures recorded, Ctrl-C safe."""

from __future__ import annotations

import hashlib
import json
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from icpflow.frames import FramePairError

from icpflow.shards.schema import shard_name
from icpflow.shards.verify import ShardError, verify_shard
from icpflow.shards.writer import write_failures, write_index, write_shard, write_text_atomic


def config_hash(config_yaml: str) -> str:
    """Short stable hash of the labeller config text."""
    return hashlib.sha256(config_yaml.encode()).hexdigest()[:16]


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


def tracked_sample(dataset, teacher, index: int, horizon: int, pair):
    """Tracker mode: teacher calls on every consecutive pair of (t .. t + horizon), chained (see teacher.tracker)."""
    from icpflow.teacher.tracker import long_horizon_flow

    steps = [dataset.pair(index, horizon=j) for j in range(1, horizon)] + [pair]
    if any(not np.array_equal(step.pc0, pair.pc0) for step in steps):
        raise ValueError(f"tracker: the pairs (t, t + j), j < {horizon}, of this sample do not start at the same scan")
    scans = [pair.pc0] + [step.pc1 for step in steps]
    grounds = [pair.ground0] + [step.ground1 for step in steps]
    if any(g is None for g in grounds):
        grounds = None
    egos, previous = None, np.eye(4)
    if all(step.ego1_from_ego0 is not None for step in steps):
        egos = []
        for step in steps:
            egos.append(step.ego1_from_ego0 @ np.linalg.inv(previous))
            previous = step.ego1_from_ego0
    result = long_horizon_flow(teacher, scans, egos, grounds, mode="tracker")
    ground0 = pair.ground0 if pair.ground0 is not None else np.zeros(len(pair.pc0), bool)
    ground1 = pair.ground1 if pair.ground1 is not None else np.zeros(len(pair.pc1), bool)
    cluster = np.full(len(pair.pc0), -1, np.int32)  # chains span several clusterings: no single id
    return result.flow, result.confidence, cluster, ground0, ground1, result.ego_k_from_0


def _sample(dataset, teacher, index: int, horizon: int, tracker: bool) -> dict:
    """One labelled sample as written to a shard (see ``icpflow.shards.schema``)."""
    pair = dataset.pair(index, horizon=horizon)
    if tracker and horizon > 1:
        flow, confidence, cluster, ground0, ground1, ego = tracked_sample(dataset, teacher, index, horizon, pair)
    else:
        result = teacher(pair.pc0, pair.pc1, ego1_from_ego0=pair.ego1_from_ego0, ground0=pair.ground0,
                         ground1=pair.ground1, time0=pair.time0, time1=pair.time1, gap=horizon, dt=pair.dt)
        flow, confidence, cluster = result.flow, result.confidence, result.labels0
        ground0, ground1, ego = result.ground0, result.ground1, result.ego1_from_ego0
    return {
        "pc0": pair.pc0, "pc1": pair.pc1,
        "ground0": np.asarray(ground0, bool), "ground1": np.asarray(ground1, bool),
        "ego1_from_ego0": np.asarray(ego, np.float64),
        "flow": np.asarray(flow, np.float32), "confidence": np.asarray(confidence, np.float32),
        "cluster": np.asarray(cluster, np.int32),
        "gt_flow": pair.flow, "gt_flow_valid": pair.flow_valid, "gt_classes": pair.classes,
        "gt_dynamic": pair.dynamic,
        "attrs": {"sample_id": pair.sample_id or dataset.sample_id(index), "log_id": pair.log_id, "index": index,
                  "timestamp0_ns": -1 if pair.timestamp0_ns is None else int(pair.timestamp0_ns),
                  "timestamp1_ns": -1 if pair.timestamp1_ns is None else int(pair.timestamp1_ns),
                  "dt": float(pair.dt)},
    }


def label_shard(job: LabelJob, shard: int, indices: list[int], ticks=None) -> dict:
    """Label ``indices`` and write shard ``shard``; a sample that raises is recorded, not fatal.

    ``ticks``: optional queue (or callable) told ``1`` after each sample, for the progress bar.

    Returns ``{"shard", "file", "samples": [{"sample_id", "index", "n0", "n1"}], "failures": [...], "seconds"}``.
    """
    from icpflow.teacher import ICPFlow

    start = time.perf_counter()
    teacher = ICPFlow(job.teacher_cfg)
    samples, records, failures = [], [], []
    for index in indices:
        try:
            sample = _sample(job.dataset, teacher, index, job.horizon, job.tracker)
        except Exception as error:  # any reader or teacher failure skips this sample only
            sample_id = _safe_id(job.dataset, index)
            source = getattr(error, "filename", None) or sample_id
            if isinstance(error, FramePairError):  # its message starts with the file it came from
                source = str(error).split(": ", 1)[0]
            reason = f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"
            failures.append({"index": index, "sample_id": sample_id, "file": str(source), "reason": reason})
        else:
            samples.append(sample)
            records.append({"sample_id": sample["attrs"]["sample_id"], "index": index,
                            "n0": int(sample["pc0"].shape[0]), "n1": int(sample["pc1"].shape[0])})
        if ticks is not None:
            (ticks if callable(ticks) else ticks.put)(1)
    name = shard_name(shard)
    write_shard(job.out_dir / name, samples, job.config_yaml, job.hash, job.compression)
    return {"shard": shard, "file": name, "samples": records, "failures": failures,
            "seconds": time.perf_counter() - start}


def _safe_id(dataset, index: int) -> str:
    try:
        return dataset.sample_id(index)
    except Exception:
        return f"index {index}"


def _state_path(out_dir: Path, shard: int) -> Path:
    return out_dir / f"{shard_name(shard)}.json"


def _record(job: LabelJob, shard: int) -> dict | None:
    try:
        record = json.loads(_state_path(job.out_dir, shard).read_text())
    except (OSError, ValueError):
        return None
    return record if record.get("config_hash") == job.hash else None


def _done(job: LabelJob, shard: int, indices: list[int]) -> dict | None:
    """The stored result of a complete, valid shard of this config covering ``indices``, or None."""
    record = _record(job, shard)
    if record is None:
        return None
    covered = sorted([r["index"] for r in record["samples"]] + [f["index"] for f in record["failures"]])
    if covered != indices:
        return None
    try:
        verify_shard(job.out_dir / record["file"], job.hash, len(record["samples"]))
    except ShardError:
        return None
    return record


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
            raise LabelError(f"{job.out_dir}: labelled with another config (hash {config_hash(marker.read_text())}, "
                             f"now {job.hash}); pass overwrite=true to relabel, or choose another out_dir")
        for state in job.out_dir.glob("shard_*.h5.json"):
            if json.loads(state.read_text()).get("config_hash") != job.hash:
                state.unlink()
                (job.out_dir / state.name[: -len(".json")]).unlink(missing_ok=True)
    for shard, _ in plan:
        name = shard_name(shard)
        for stale in [*job.out_dir.glob(f"{name}.tmp-*"), *job.out_dir.glob(f"{name}.json.tmp-*")]:
            stale.unlink(missing_ok=True)
        if overwrite:
            _state_path(job.out_dir, shard).unlink(missing_ok=True)
            (job.out_dir / name).unlink(missing_ok=True)
    write_text_atomic(marker, job.config_yaml)


class LabelError(RuntimeError):
    """A labelling run cannot start (config mismatch, bad runner). The message is one line."""


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
    write_index(job.out_dir / "index.json", {
        "config_hash": job.hash,
        "shards": [{"file": r["file"], "samples": r["samples"]} for r in records if r["samples"]]})
    failures = [f for r in records for f in r["failures"]]
    write_failures(job.out_dir / "failures.jsonl", failures)
    return failures


def _end_helpers() -> None:
    """Terminate the child processes a worker's libraries started (hdbscan's joblib pool idles for minutes and
    would otherwise keep the worker, and so the pool, from exiting)."""
    import multiprocessing

    for child in multiprocessing.active_children():
        child.terminate()


def _worker_init() -> None:
    from multiprocessing.util import Finalize

    Finalize(None, _end_helpers, exitpriority=100)


def _pool_results(job, todo, workers, tick):
    """Shard results from a spawn process pool, as they finish; per-sample ticks go to ``tick``."""
    context = get_context("spawn")
    with context.Manager() as manager, ProcessPoolExecutor(workers, mp_context=context, initializer=_worker_init) as pool:
        queue = manager.Queue()
        pending = {pool.submit(label_shard, job, shard, indices, queue) for shard, indices in todo}
        try:
            while pending:
                finished, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                while not queue.empty():
                    tick(queue.get())
                for future in finished:
                    yield future.result()
        finally:
            for future in pending:
                future.cancel()


def _ray_results(job, todo, address, workers, tick):
    """Shard results from Ray tasks (one per shard, 1 CPU each), as they finish; ticks per shard."""
    import ray

    if not ray.is_initialized():
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    remote = ray.remote(num_cpus=1)(label_shard)
    pending = [remote.remote(job, shard, indices) for shard, indices in todo]
    try:
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            result = ray.get(ready[0])
            tick(len(result["samples"]) + len(result["failures"]))
            yield result
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)


def run_labelling(job: LabelJob, plan: list[tuple[int, list[int]]], workers: int = 1, runner: str = "local",
                  ray_address: str | None = None, overwrite: bool = False, progress: bool = True) -> dict:
    """Label every shard of ``plan`` not already complete; then write ``index.json`` and ``failures.jsonl``.

    Each finished shard is recorded at once (``shard_XXXXXX.h5.json``), so a killed run loses only shards in
    flight. Returns ``{"done", "skipped", "failed", "seconds_per_sample", "failures"}``: samples labelled now,
    samples of shards found complete, failed samples of this plan, mean teacher+reader seconds per labelled sample.
    """
    from tqdm import tqdm

    if runner not in ("local", "ray"):
        raise LabelError(f"runner must be local or ray, got {runner!r}")
    prepare(job, plan, overwrite)
    results, todo = {}, []
    for shard, indices in plan:
        record = _done(job, shard, indices)
        if record is None:
            todo.append((shard, indices))
        else:
            results[shard] = record
    skipped = sum(len(r["samples"]) for r in results.values())
    seconds, done = 0.0, 0
    bar = tqdm(total=sum(len(indices) for _, indices in todo), unit="sample", disable=not progress,
               dynamic_ncols=True, desc="labelling")
    if runner == "ray":
        stream = _ray_results(job, todo, ray_address, workers, bar.update)
    elif workers > 1 and len(todo) > 1:
        stream = _pool_results(job, todo, workers, bar.update)
    else:
        stream = (label_shard(job, shard, indices, bar.update) for shard, indices in todo)
    try:
        for result in stream:
            write_text_atomic(_state_path(job.out_dir, result["shard"]),
                              json.dumps({**result, "config_hash": job.hash}, sort_keys=True))
            results[result["shard"]] = result
            seconds += result["seconds"]
            done += len(result["samples"])
    finally:
        bar.close()
        write_manifests(job)
    failures = [f for shard in sorted(results) for f in results[shard]["failures"]]
    return {"done": done, "skipped": skipped, "failed": len(failures),
            "seconds_per_sample": seconds / done if done else 0.0, "failures": failures}
