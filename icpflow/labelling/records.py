"""What a labelling run keeps on disk besides the shards: each shard's record (``shard_XXXXXX.h5.json``: its
samples, failures and the reader's ids of its indices), the resume decisions made from them, the ``out_dir``
marker (``config.yaml``) and the manifests (``index.json``, ``failures.jsonl``)."""

from __future__ import annotations

import json
from pathlib import Path

import yaml

from icpflow.core.atomic import write_text_atomic
from icpflow.core.files import read_text
from icpflow.datasets.base import sample_id_or_index
from icpflow.labelling.job import LabelError, LabelJob, config_hash
from icpflow.shards.schema import shard_name
from icpflow.shards.verify import ShardError, verify_shard
from icpflow.shards.writer import write_failures, write_index, write_shard

#: failure reason of a sample during which a worker process died
DIED = (
    "WorkerDied: the worker process died labelling this sample (killed, e.g. out of memory, or crashed in native code)"
)
#: a sample that killed its worker this many times in a row is not tried again (``overwrite=true`` does)
MAX_DEATHS = 2


def record_path(out_dir: Path, shard: int) -> Path:
    """The record of shard ``shard``: ``shard_XXXXXX.h5.json``."""
    return out_dir / f"{shard_name(shard)}.json"


def read_record(job: LabelJob, shard: int) -> dict | None:
    """The record of ``shard`` written with this job's config, or None."""
    try:
        record = json.loads(read_text(record_path(job.out_dir, shard)))
    except (OSError, ValueError):
        return None
    return record if record.get("config_hash") == job.hash else None


def finished(job: LabelJob, shard: int, indices: list[int], ids: list[str]) -> dict | None:
    """The record of a complete, valid shard of this config covering ``indices`` whose reader sample ids were
    ``ids`` when it was labelled, or None (its failed samples may still be worth retrying: :func:`retried`)."""
    record = read_record(job, shard)
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


def retried(record: dict) -> tuple[list[int], dict]:
    """The failed samples of a shard record to label again, and ``{index: failure}`` of those that are not: the
    samples that killed their worker ``MAX_DEATHS`` times in a row."""
    lost = {f["index"]: f for f in record["failures"] if f.get("deaths", 0) >= MAX_DEATHS}
    return [f["index"] for f in record["failures"] if f["index"] not in lost], lost


def died(dataset, index: int, previous: dict | None) -> dict:
    """The failure record of sample ``index`` that killed its worker (counting deaths in a row across runs:
    ``previous`` is the shard's earlier record, or None)."""
    before = next((f for f in (previous or {}).get("failures", ()) if f["index"] == index), {})
    deaths = before.get("deaths", 0) + 1
    reason = DIED if deaths < MAX_DEATHS else f"{DIED}; {deaths} times in a row, not tried again (overwrite=true does)"
    sample_id = sample_id_or_index(dataset, index)
    return {"index": index, "sample_id": sample_id, "file": sample_id, "reason": reason, "deaths": deaths}


def write_shard_and_record(
    job: LabelJob,
    shard: int,
    indices: list[int],
    samples: list[dict],
    failures: list[dict],
    reused: int,
    seconds: float,
) -> dict:
    """Write shard ``shard`` (``samples``, shard rows in index order), then its record; returns the record: ``{"shard",
    "file", "samples": [{"sample_id", "index", "n0", "n1"}], "failures", "reused", "seconds", "config_hash",
    "ids"}`` (``ids``: the reader's sample ids of ``indices``; ``reused``: samples copied from an earlier file)."""
    name = shard_name(shard)
    write_shard(job.out_dir / name, samples, job.config_yaml, job.hash, job.compression)
    record = {
        "shard": shard,
        "file": name,
        "samples": [
            {
                "sample_id": str(sample["attrs"]["sample_id"]),
                "index": int(sample["attrs"]["index"]),
                "n0": int(sample["pc0"].shape[0]),
                "n1": int(sample["pc1"].shape[0]),
            }
            for sample in samples
        ],
        "failures": failures,
        "reused": reused,
        "seconds": seconds,
        "config_hash": job.hash,
        "ids": [sample_id_or_index(job.dataset, i) for i in indices],
    }
    write_text_atomic(record_path(job.out_dir, shard), json.dumps(record, sort_keys=True))
    return record


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


def remove_temporaries(out_dir: Path, shard: int) -> None:
    """Leftover temporary files of shard ``shard`` and its record (from a killed run)."""
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
    stored = read_text(marker) if marker.exists() else None
    if stored is not None and config_hash(stored) != job.hash:
        if not overwrite:
            raise LabelError(
                f"{job.out_dir}: labelled with another config (hash {config_hash(stored)}, "
                f"now {job.hash}: {config_changes(stored, job.config_yaml)}); pass "
                f"overwrite=true to relabel, or choose another out_dir"
            )
        for state in job.out_dir.glob("shard_*.h5.json"):
            if json.loads(read_text(state)).get("config_hash") != job.hash:
                state.unlink()
                (job.out_dir / state.name[: -len(".json")]).unlink(missing_ok=True)
    for shard, _ in plan:
        remove_temporaries(job.out_dir, shard)
        if overwrite:
            record_path(job.out_dir, shard).unlink(missing_ok=True)
            (job.out_dir / shard_name(shard)).unlink(missing_ok=True)
    write_text_atomic(marker, job.config_yaml)


def write_manifests(job: LabelJob, planned: int | None = None, stopped: bool = False) -> list[dict]:
    """``index.json`` and ``failures.jsonl`` from every finished shard of this config in ``out_dir``.

    Reads all shard records, so concurrent jobs (one per SLURM array task) each leave a complete index behind
    when they finish last. The index says how complete the folder is: ``planned`` samples (the whole dataset or
    ``limit``), ``labelled`` and ``failed`` ones, and ``complete`` (every planned sample tried and the run not
    stopped), which ``train.py`` and ``eval.py`` read and say. Returns the failures.
    """
    records = []
    for state in sorted(job.out_dir.glob("shard_*.h5.json")):
        record = json.loads(read_text(state))
        if record.get("config_hash") == job.hash:
            records.append(record)
    failures = [f for r in records for f in r["failures"]]
    labelled = sum(len(r["samples"]) for r in records)
    write_index(
        job.out_dir / "index.json",
        {
            "config_hash": job.hash,
            "shards": [{"file": r["file"], "samples": r["samples"]} for r in records if r["samples"]],
            "planned": planned,
            "labelled": labelled,
            "failed": len(failures),
            "complete": bool(not stopped and planned is not None and labelled + len(failures) >= planned),
        },
    )
    write_failures(job.out_dir / "failures.jsonl", failures)
    return failures
