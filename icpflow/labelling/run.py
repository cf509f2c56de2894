"""Label shards with the teacher: one sample is the unit of work (``icpflow.labelling.sample``), labelled by an
executor (``icpflow.labelling.executors``: this process, a local process pool or Ray); this process assembles each
shard from its samples as they come back and writes it with its record (``icpflow.labelling.records``) at once, so
the run is resumable, records its failures and stops cleanly on Ctrl-C or SIGTERM."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from icpflow.core.threads import available_cores
from icpflow.datasets.base import sample_id_or_index
from icpflow.labelling.executors import in_process, local_pool, ray_tasks
from icpflow.labelling.job import LabelJob
from icpflow.labelling.records import died, finished, prepare, retried, write_manifests, write_shard_and_record
from icpflow.labelling.trajectory import drive_trajectory
from icpflow.shards.reader import read_shard_samples
from icpflow.shards.schema import shard_name


@dataclass
class ShardWork:
    """A shard being labelled: its plan ``indices``, the samples still ``waiting`` to come back, the shard rows and
    failure records of those that did (by index; ``failures`` starts with the samples not tried again), and its
    ``previous`` record (its labelled samples are copied from the earlier file) or None."""

    shard: int
    indices: list[int]
    waiting: set[int]
    previous: dict | None = None
    samples: dict[int, dict] = field(default_factory=dict)
    failures: dict[int, dict] = field(default_factory=dict)
    seconds: float = 0.0

    def write(self, job: LabelJob) -> dict:
        """Write the complete shard (earlier samples copied, new ones, in index order) and its record."""
        kept = {}
        if self.previous is not None:
            kept = {int(s["attrs"]["index"]): s for s in read_shard_samples(job.out_dir / shard_name(self.shard))}
        rows = {**kept, **self.samples}
        return write_shard_and_record(
            job,
            self.shard,
            self.indices,
            [rows[i] for i in self.indices if i in rows],
            [self.failures[i] for i in self.indices if i in self.failures],
            len(kept),
            self.seconds,
        )


def run_labelling(
    job: LabelJob,
    plan: list[tuple[int, list[int]]],
    workers: int = 1,
    runner: str = "local",
    ray_address: str | None = None,
    overwrite: bool = False,
    progress: bool = True,
    planned: int | None = None,
) -> dict:
    """Label every sample of ``plan`` not already labelled; then write ``index.json`` and ``failures.jsonl``.

    ``runner``: "local" (validated by the caller, ``icpflow.labelling.cli``) or "ray". Each shard is written with
    its record (``shard_XXXXXX.h5.json``, with the reader's sample ids of its indices) as soon as its last sample
    comes back, so a killed run loses only the shards still in flight. A rerun labels the samples that failed
    before (a fixed input file, a transient death) and keeps the others of their shard, except samples that killed
    their worker ``MAX_DEATHS`` times in a row. ``workers`` local processes share the available cores (each runs
    the teacher on ``cores // workers`` threads); with one, samples are labelled in this process. Returns
    ``{"done", "skipped", "failed", "seconds_per_sample", "seconds", "failures"}``: samples labelled now, samples
    labelled by an earlier run, failed samples of this plan, mean reader + teacher seconds per labelled sample in a
    worker, wall-clock seconds. ``index.json`` is written on every exit (also on Ctrl-C or an error), from the
    shards then on disk, with its completeness (``planned``: the samples of the whole labelling, every job of an
    array included; default: this plan's).
    """
    from icpflow.core.console import Progress

    start = time.perf_counter()
    prepare(job, plan, overwrite)
    drive_trajectory(job, progress, overwrite)  # a drive without poses: its ego motion, once, before its pairs
    results, open_shards, skipped = {}, [], 0
    for shard, indices in plan:
        record = finished(job, shard, indices, [sample_id_or_index(job.dataset, i) for i in indices])
        if record is None:
            open_shards.append(ShardWork(shard, indices, set(indices)))
            continue
        retry, lost = retried(record)
        skipped += len(record["samples"])
        if retry:
            open_shards.append(ShardWork(shard, indices, set(retry), record, failures=dict(lost)))
        else:
            results[shard] = record
    tasks = [index for work in open_shards for index in work.indices if index in work.waiting]
    shard_of = {index: work for work in open_shards for index in work.waiting}
    bar = Progress(
        total=len(tasks),
        unit=" samples",
        disable=not progress,
        dynamic_ncols=True,
        desc="labelling",
        bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}, {rate_noinv_fmt}]",
    )
    parallel = max(1, min(workers, len(tasks)))
    if runner == "ray":
        stream = ray_tasks(job, tasks, ray_address, workers)
    elif workers > 1 and tasks:  # worker processes even for one sample: one that kills its process must not end the run
        stream = local_pool(job, tasks, parallel, max(1, available_cores() // parallel))
    else:
        stream = in_process(job, tasks, available_cores())
    seconds, done, stopped = 0.0, 0, True
    try:
        for outcome in stream:
            index = outcome["index"]
            work = shard_of[index]
            work.seconds += outcome["seconds"]
            if "sample" in outcome:
                work.samples[index] = outcome["sample"]
            else:
                work.failures[index] = outcome.get("failure") or died(job.dataset, index, work.previous)
            work.waiting.discard(index)
            bar.update(1)
            if not work.waiting:
                results[work.shard] = work.write(job)
                seconds += work.seconds
                done += len(work.samples)
        stopped = False
    finally:
        stream.close()
        bar.close()
        try:
            total = sum(len(indices) for _, indices in plan) if planned is None else planned
            write_manifests(job, total, stopped)
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
