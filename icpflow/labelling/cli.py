"""``label.py``: from the Hydra config to a labelling run, a summary and an exit status."""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from icpflow.labelling.plan import plan_shards
from icpflow.labelling.run import LabelError, LabelJob, run_labelling


def teacher_config(cfg: DictConfig):
    """``ICPFlowConfig``: the dataset's preset, then ``dataset.teacher``, then non-null ``icpflow.*`` fields.

    A ``dataset.teacher`` key that is not a teacher field is an error (ValueError naming it).
    """
    from icpflow.teacher.config import ICPFlowConfig, from_hydra

    known = {f.name for f in dataclasses.fields(ICPFlowConfig)}
    block = cfg.dataset.get("teacher")
    per_dataset = OmegaConf.to_container(block, resolve=True) if block is not None else {}
    unknown = sorted(set(per_dataset) - known)
    if unknown:
        raise ValueError(f"dataset {cfg.dataset.name}: dataset.teacher has keys that are not ICPFlowConfig fields: "
                         f"{', '.join(unknown)}")
    values = dict(per_dataset)
    chosen = OmegaConf.to_container(cfg.icpflow, resolve=True)
    values.update({key: value for key, value in chosen.items() if value is not None})
    return from_hydra(values)


def labeller_yaml(cfg: DictConfig, teacher) -> str:
    """The config that determines the labels (hashed): dataset reader minus its root, teacher fields, horizon,
    tracker, shard size. Paths, workers, runner, limit and compression do not change labels and are left out."""
    reader = OmegaConf.to_container(cfg.dataset.reader, resolve=True)
    reader.pop("root", None)
    content = {"dataset": {"name": cfg.dataset.name, "reader": reader}, "split": cfg.split,
               "teacher": dataclasses.asdict(teacher), "horizon": int(cfg.horizon), "tracker": bool(cfg.tracker),
               "shard_size": int(cfg.shard_size)}
    return OmegaConf.to_yaml(OmegaConf.create(content), sort_keys=True)


def open_dataset(cfg: DictConfig):
    """Instantiate the reader; a missing or empty root becomes one line (LabelError)."""
    from hydra.utils import instantiate

    name = cfg.dataset.name
    root = cfg.dataset.get("root", None) if not OmegaConf.is_missing(cfg.dataset, "root") else "???"
    if root == "???":
        raise LabelError(f"dataset {name}: dataset.root is not set (pass dataset.root=/path/to/{name})")
    if root is not None:
        path = Path(root)
        if not path.is_dir():
            raise LabelError(f"dataset {name}: root {path} does not exist or is not a directory")
        if not any(path.iterdir()):
            raise LabelError(f"dataset {name}: root {path} is empty")
    try:
        dataset = instantiate(cfg.dataset.reader)
    except Exception as error:  # hydra wraps the reader's own one-line error
        cause = error.__cause__ or error
        raise LabelError(f"dataset {name}: {str(cause).splitlines()[0] if str(cause) else type(cause).__name__}")
    if len(dataset) == 0:
        raise LabelError(f"dataset {name}: no samples under {root} (split {cfg.split})")
    return dataset


def label(cfg: DictConfig, progress: bool = True) -> int:
    """Run the labelling stage of ``cfg`` (conf/label.yaml); print the summary; return the exit status.

    0: all samples labelled; 1: some samples failed (see failures.jsonl); 2: the run could not start;
    130: interrupted (only complete shards are kept).
    """
    try:
        dataset = open_dataset(cfg)
        teacher = teacher_config(cfg)
        if int(cfg.horizon) > getattr(dataset, "max_horizon", 1):
            raise LabelError(f"dataset {cfg.dataset.name}: horizon={cfg.horizon} exceeds its max_horizon "
                             f"{dataset.max_horizon}")
        workers = int(cfg.workers) if cfg.workers else os.cpu_count() or 1
        job = LabelJob(dataset, teacher, Path(cfg.out_dir), labeller_yaml(cfg, teacher), int(cfg.horizon),
                       bool(cfg.tracker), cfg.compression)
        plan = plan_shards(len(dataset), int(cfg.shard_size), cfg.limit, int(cfg.shard_index), int(cfg.num_shards))
        summary = run_labelling(job, plan, workers, cfg.runner, cfg.ray.address, bool(cfg.overwrite), progress)
    except (LabelError, ValueError) as error:
        print(f"label: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("label: interrupted; complete shards are kept, rerun the same command to resume", file=sys.stderr)
        return 130
    print(f"label: {summary['done']} samples labelled, {summary['skipped']} skipped (already done), "
          f"{summary['failed']} failed, {summary['seconds_per_sample']:.2f} s/sample -> {job.out_dir}")
    for failure in summary["failures"][:10]:
        print(f"  failed {failure['sample_id']} ({failure['file']}): {failure['reason']}", file=sys.stderr)
    return 1 if summary["failed"] else 0
