"""``icpflow-label`` and ``label.py`` (:func:`main`): from the Hydra config to a labelling run, a summary and an
exit status (:func:`label`)."""

from __future__ import annotations

import dataclasses
import importlib.util
import signal
import sys
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from icpflow.core.atomic import WriteError
from icpflow.core.console import quiet
from icpflow.core.entry_points import hydra_entry
from icpflow.core.errors_and_signals import (
    STOPS,
    one_line,
    reported,
    stop_on_signals,
    stop_signum,
    stopped_by,
)
from icpflow.core.settings import check_config
from icpflow.core.threads import available_cores
from icpflow.datasets.from_config import dataset_root, open_dataset
from icpflow.labelling.job import LabelError, LabelJob
from icpflow.labelling.labeller import identity
from icpflow.labelling.options import register
from icpflow.labelling.plan import plan_shards
from icpflow.labelling.run import run_labelling
from icpflow.scans.preprocess import Preprocessing
from icpflow.teacher.config import teacher_config
from icpflow.teacher.warmup import ensure_compiled

#: failed samples listed at the end of a run (the rest: failures.jsonl)
SHOWN_FAILURES = 10


def labeller_yaml(cfg: DictConfig, teacher, labeller: dict | None = None) -> str:
    """The config that identifies a run (hashed): which samples are read (dataset reader, its absolute root,
    split), the teacher fields, horizon, tracker and shard size, and a labeller other than the teacher
    (``icpflow.labelling.labeller.identity``: its block, checkpoint and the checkpoint's hash). Workers, runner,
    limit, the job split and compression change neither the samples nor the labels and are left out."""
    reader = OmegaConf.to_container(cfg.dataset.reader, resolve=True)
    reader.pop("root", None)
    content = {
        "dataset": {"name": cfg.dataset.name, "root": dataset_root(cfg), "reader": reader},
        "split": cfg.split,
        "teacher": dataclasses.asdict(teacher),
        "preprocessing": Preprocessing.from_teacher(
            teacher
        ).to_dict(),  # what a student needs (icpflow.scans.preprocess)
        "horizon": int(cfg.horizon),
        "tracker": bool(cfg.tracker),
        "shard_size": int(cfg.shard_size),
    }
    if labeller is not None:  # absent for the teacher: the runs made before labellers keep their hash
        content["labeller"] = labeller
    return OmegaConf.to_yaml(OmegaConf.create(content), sort_keys=True)


def check_options(cfg: DictConfig) -> str | None:
    """Check ``cfg`` against its schema's rules (``icpflow.labelling.options.LabelOptions``) and what they cannot say
    (the ray
    package for ``runner=ray``); returns the compression filter (None: uncompressed)."""
    check_config(cfg)
    if cfg.runner == "ray" and importlib.util.find_spec("ray") is None:
        raise LabelError("runner=ray needs the ray package, which is not installed (pip install 'ray>=2.9')")
    return None if cfg.compression in (None, "none") else cfg.compression


def label(cfg: DictConfig, progress: bool = True) -> int:
    """Run the labelling stage of ``cfg`` (conf/label.yaml); print the summary; return the exit status.

    0: all samples labelled; 1: some samples failed (see failures.jsonl); 2: the run could not start or go on
    (e.g. a full disk); 130: interrupted (Ctrl-C), 143: terminated (SIGTERM), both keeping the complete shards
    and a consistent index.json. Every error is one line on stderr.
    """
    with stop_on_signals():  # SIGTERM and Ctrl-C raise Stop here: the executors end their workers as it unwinds
        try:
            compression = check_options(cfg)
            teacher = teacher_config(cfg)
            horizon = int(cfg.horizon)
            if horizon > teacher.pairing.max_frame_gap:
                raise LabelError(
                    f"horizon={horizon} exceeds the teacher's max_frame_gap {teacher.pairing.max_frame_gap} "
                    f"(icpflow.pairing.max_frame_gap=...)"
                )
            labeller = identity(OmegaConf.to_container(cfg.labeller, resolve=True))
            if labeller is not None and (horizon != 1 or cfg.tracker):
                raise LabelError(f"labeller={labeller['name']} labels pairs one frame apart: horizon=1, tracker=false")
            dataset = open_dataset(cfg, horizon)
            workers = int(cfg.workers) if cfg.workers else available_cores()
            job = LabelJob(
                dataset,
                teacher,
                Path(cfg.out_dir),
                labeller_yaml(cfg, teacher, labeller),
                horizon,
                bool(cfg.tracker),
                compression,
                labeller,
            )
            plan = plan_shards(len(dataset), int(cfg.shard_size), cfg.limit, int(cfg.shard_index), int(cfg.num_shards))
            ensure_compiled("label")  # once per environment, here rather than in every worker's first sample
            planned = len(dataset) if cfg.limit is None else min(len(dataset), int(cfg.limit))
            summary = run_labelling(
                job, plan, workers, cfg.runner, cfg.ray.address, bool(cfg.overwrite), progress, planned
            )
        except WriteError as error:  # disk full, no permission: the file and the cause
            print(
                f"label: {error}; complete shards are kept in {cfg.out_dir}, fix this and rerun the same command to "
                "resume",
                file=sys.stderr,
            )
            return 2
        except (LabelError, ValueError, OSError) as error:  # OSError: out_dir not creatable, unreadable input
            print(f"label: {one_line(error)}", file=sys.stderr)
            return 2
        except STOPS as caught:  # SIGTERM or Ctrl-C (also inside a kernel)
            signum = stop_signum(stopped_by(caught))
            what = "terminated (SIGTERM)" if signum == signal.SIGTERM else "interrupted"
            print(
                f"label: {what}; complete shards are kept in {cfg.out_dir}, rerun the same command to resume",
                file=sys.stderr,
            )
            return 128 + signum
    print(summary_line(summary, job.out_dir))
    failures = summary["failures"]
    for failure in failures[:SHOWN_FAILURES]:
        print(f"  failed {failure['sample_id']} ({failure['file']}): {failure['reason']}", file=sys.stderr)
    if len(failures) > SHOWN_FAILURES:
        print(
            f"  ... and {len(failures) - SHOWN_FAILURES} more (all in {job.out_dir / 'failures.jsonl'})",
            file=sys.stderr,
        )
    return 1 if summary["failed"] else 0


def summary_line(summary: dict, out_dir: Path) -> str:
    """The end-of-run line: samples done, skipped and failed, mean worker s/sample, samples/s over the wall time."""
    rate = summary["done"] / summary["seconds"] if summary["seconds"] > 0 else 0.0
    return (
        f"label: {summary['done']} samples labelled, {summary['skipped']} skipped (already done), "
        f"{summary['failed']} failed; mean {summary['seconds_per_sample']:.2f} s/sample per worker, "
        f"{rate:.2f} samples/s in {summary['seconds']:.1f} s -> {out_dir}"
    )


def labelling_task(cfg: DictConfig) -> None:
    """The Hydra task of :func:`main`: :func:`label`, exiting with its status."""
    quiet()
    with reported("label"):
        status = label(cfg)
        if status == 1 and HydraConfig.get().mode == RunMode.MULTIRUN:
            return  # failed samples are in failures.jsonl and the summary; the sweep goes on with its other jobs
        if status:
            sys.exit(status)


def main() -> None:
    """``icpflow-label`` and ``label.py``: label a dataset as ``conf/label.yaml`` and the command line say."""
    register()  # label_schema in Hydra's ConfigStore: the structured config conf/label.yaml extends
    hydra_entry("label", "label", labelling_task)
