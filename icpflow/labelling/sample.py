"""One sample, the unit of work of a labelling run: the teacher on its pair, turned into the rows of a shard
(``icpflow.shards.schema``), or a failure record when the reader or the teacher raises."""

from __future__ import annotations

import time

import numpy as np

from icpflow.core.frame_pair import FramePairError
from icpflow.core.stops import raise_stop_behind
from icpflow.core.threads import thread_limit
from icpflow.datasets.base import sample_id_or_index
from icpflow.labelling.labeller import build_labeller
from icpflow.teacher.long_horizon import SampleFlow, teacher_on_sample


def build_teacher(cfg, threads: int):
    """The teacher of ``cfg`` with hdbscan on at most ``threads`` processes (the labels do not change)."""
    from icpflow import teacher

    return teacher.ICPFlow(cfg.replace(**{"clustering.n_jobs": min(cfg.clustering.n_jobs, threads)}))


def shard_rows(dataset, index: int, pair, labels: SampleFlow) -> dict:
    """Sample ``index`` as written to a shard: the reader's pair, its ground truth and the teacher's ``labels``."""
    return {
        "pc0": pair.pc0,
        "pc1": pair.pc1,
        "ground0": labels.ground0,
        "ground1": labels.ground1,
        "ego1_from_ego0": labels.ego1_from_ego0,
        "flow": labels.flow,
        "confidence": labels.confidence,
        "cluster": labels.cluster,
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


class NonFiniteLabels(ValueError):
    """The teacher's labels of a sample hold NaN or Inf: the sample fails, nothing non-finite is written."""


def check_finite_labels(labels: SampleFlow) -> None:
    """Raise :class:`NonFiniteLabels` (one line naming the arrays) unless flow, confidence and ego motion are
    finite: a shard never holds a non-finite pseudo-label (``verify_shard`` refuses one too)."""
    bad = [
        f"{name} ({int((~np.isfinite(value)).sum())} values)"
        for name, value in (
            ("flow", labels.flow),
            ("confidence", labels.confidence),
            ("ego1_from_ego0", labels.ego1_from_ego0),
        )
        if not np.isfinite(value).all()
    ]
    if bad:
        raise NonFiniteLabels(f"the labeller's labels are not finite: {', '.join(bad)}")


def failure_record(dataset, index: int, pair, error: Exception) -> dict:
    """``{"index", "sample_id", "file", "reason"}`` of a sample whose reader or teacher raised ``error``: the pair's
    id, or the reader's ``sample_id(index)`` when the pair could not be read; the file the error names, else the id."""
    sample_id = pair.sample_id if pair is not None and pair.sample_id else sample_id_or_index(dataset, index)
    source = getattr(error, "filename", None) or sample_id
    if isinstance(error, FramePairError) and pair is None:  # a reader's: its message starts with the file
        source = str(error).split(": ", 1)[0]
    reason = f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"
    return {"index": index, "sample_id": sample_id, "file": str(source), "reason": reason}


def label_sample(job, index: int, threads: int) -> dict:
    """Label sample ``index`` of ``job`` with its labeller (the teacher, or ``job.labeller``'s) on at most
    ``threads`` threads (numba, BLAS, hdbscan's n_jobs, torch). Returns ``{"index", "seconds", "sample": shard
    rows}`` or, when the reader or the labeller raises, ``{"index", "seconds", "failure": record}``
    (:func:`failure_record`): a bad sample is not fatal."""
    start = time.perf_counter()
    pair = None
    try:
        torch_too = job.labeller is not None or job.teacher_cfg.icp.backend == "torch"
        with thread_limit(threads, torch_too=torch_too):
            pair = job.dataset.pair(index, horizon=job.horizon)
            if job.labeller is None:
                teacher = build_teacher(job.teacher_cfg, threads)
                labels = teacher_on_sample(teacher, job.dataset, index, pair, job.horizon, job.tracker)
            else:
                labels = build_labeller(job.labeller, threads, job.teacher_cfg)(job.dataset, index, pair, job.horizon)
        check_finite_labels(labels)
        outcome = {"sample": shard_rows(job.dataset, index, pair, labels)}
    except Exception as error:  # any reader or teacher failure skips this sample only
        raise_stop_behind(error)
        outcome = {"failure": failure_record(job.dataset, index, pair, error)}
    return {"index": index, "seconds": time.perf_counter() - start, **outcome}
