"""Evaluate scene-flow methods on a dataset with ground truth: one table, a row per method (``eval.py``).

A method is a callable ``method(pair, index) -> (N0, 3) float32 FULL flow`` (project convention, pc0's ego frame
of t -> positions in the ego frame of t + dt), built by :func:`build_method` from its name:

- ``zero``: zero full flow; ``ego``: ego flow only (every point static in the world);
- ``icpflow``: the teacher (``conf/icpflow``), ``tracker=true`` chains it through intermediate frames;
- ``student``: a FastFlow3D checkpoint or export (``checkpoint=``), through ``fastflow3d.predictor.Predictor``;
- ``shards``: the pseudo-labels a ``label.py`` run wrote (``shards=<out_dir>``), matched by sample id.

Every method sees the same pairs; each pair's metric sums go into a :class:`MethodScores` (the paper's splits,
point-weighted and per pair; AV2 Threeway and bucketed normalised EPE; seconds per pair). A pair whose reading or
prediction raises is recorded in ``failures`` and skipped for every method, so all rows score the same pairs.
"""

from __future__ import annotations

import csv
import io
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from icpflow import metrics
from icpflow.baselines import ego_only_flow, zero_flow
from icpflow.frames import FramePair

METHODS = ("zero", "ego", "icpflow", "student", "shards")
Method = Callable[[FramePair, int], np.ndarray]


class EvaluationError(ValueError):
    """A one-line reason why the evaluation cannot start."""


# ---------------------------------------------------------------------------------------------------- methods

class TeacherMethod:
    """The ICP-Flow teacher with the pair's own ego motion and ground masks when it has them."""

    def __init__(self, config, dataset, horizon: int = 1, tracker: bool = False):
        from icpflow.teacher import ICPFlow

        self.teacher, self.dataset, self.horizon, self.tracker = ICPFlow(config), dataset, horizon, tracker

    def __call__(self, pair: FramePair, index: int) -> np.ndarray:
        if self.tracker and self.horizon > 1:
            from icpflow.labelling.run import tracked_sample

            return tracked_sample(self.dataset, self.teacher, index, self.horizon, pair)[0]
        return self.teacher(pair.pc0, pair.pc1, ego1_from_ego0=pair.ego1_from_ego0, ground0=pair.ground0,
                            ground1=pair.ground1, time0=pair.time0, time1=pair.time1, gap=self.horizon,
                            dt=pair.dt).flow


class ShardMethod:
    """Pseudo-labels stored by ``label.py``: the stored flow of the sample with the same id and the same pc0."""

    def __init__(self, out_dir):
        from icpflow.shards.reader import ShardDataset

        try:
            self.shards = ShardDataset(out_dir)
        except FileNotFoundError as error:
            raise EvaluationError(str(error)) from None
        self.by_id = {sample_id: i for i, sample_id in enumerate(self.shards.sample_ids)}
        if not self.by_id:
            raise EvaluationError(f"{out_dir}: the shards hold no samples")

    def __call__(self, pair: FramePair, index: int) -> np.ndarray:
        position = self.by_id.get(pair.sample_id)
        if position is None:
            raise KeyError(f"{self.shards.root}: no stored sample {pair.sample_id!r}")
        stored = self.shards[position]
        if stored["pc0"].shape != pair.pc0.shape or not np.allclose(stored["pc0"], pair.pc0, atol=1e-5):
            raise ValueError(f"{self.shards.root}: sample {pair.sample_id!r} was labelled on other points")
        return stored["flow"]


class StudentMethod:
    """A trained FastFlow3D (checkpoint or export), given the pair's ego motion (estimated when absent)."""

    def __init__(self, path):
        from fastflow3d.predictor import Predictor

        self.predictor = Predictor.load(path)

    def __call__(self, pair: FramePair, index: int) -> np.ndarray:
        return self.predictor(pair.pc0, pair.pc1, pair.ego1_from_ego0)


def build_method(name: str, *, dataset=None, teacher_config=None, horizon: int = 1, tracker: bool = False,
                 checkpoint=None, shards=None) -> Method:
    """The method called ``name`` (one of ``METHODS``) as ``method(pair, index) -> full flow``."""
    if name == "zero":
        return lambda pair, index: zero_flow(pair)
    if name == "ego":
        return lambda pair, index: ego_only_flow(pair)
    if name == "icpflow":
        return TeacherMethod(teacher_config, dataset, horizon, tracker)
    if name == "student":
        if not checkpoint:
            raise EvaluationError("method student needs checkpoint=<.ckpt or export>")
        if not Path(checkpoint).exists():
            raise EvaluationError(f"{checkpoint}: checkpoint does not exist")
        return StudentMethod(checkpoint)
    if name == "shards":
        if not shards:
            raise EvaluationError("method shards needs shards=<a label.py out_dir>")
        return ShardMethod(shards)
    raise EvaluationError(f"unknown method {name!r}, expected one of {', '.join(METHODS)}")


# ---------------------------------------------------------------------------------------------------- scores

@dataclass
class MetricOptions:
    """How pairs are scored: ``crop`` half-width of the xy box (m, None = all), ground, relative error base,
    ``class_to_meta`` (dataset classes -> AV2 meta-classes; None: no bucketed EPE, Threeway foreground = class > 0)."""

    crop: float | None = 32.0
    include_ground: bool = False
    relative_to: str = "residual"
    dynamic_speed: float = 0.5
    class_to_meta: dict[int, str] | None = None


@dataclass
class MethodScores:
    """Running sums of one method over the pairs seen so far."""

    paper: metrics.MetricAccumulator = field(default_factory=metrics.MetricAccumulator)
    buckets: np.ndarray | None = None
    threeway: np.ndarray | None = None
    seconds: list[float] = field(default_factory=list)

    def add(self, pair: FramePair, flow: np.ndarray, seconds: float, options: MetricOptions) -> None:
        self.paper.add(metrics.frame_pair_stats(pair, flow, crop=options.crop, include_ground=options.include_ground,
                                                relative_to=options.relative_to,
                                                dynamic_speed=options.dynamic_speed))
        common = dict(ground=None if options.include_ground else pair.ground0, flow_valid=pair.flow_valid)
        threeway_meta = {0: "BACKGROUND"} | {int(c): "FOREGROUND" for c in np.unique(pair.classes) if c > 0}
        if options.class_to_meta is not None:
            threeway_meta = {c: "BACKGROUND" if m == "BACKGROUND" else "FOREGROUND"
                             for c, m in options.class_to_meta.items()}
            buckets = metrics.av2_bucket_stats(pair.pc0, flow, pair.flow, pair.ego1_from_ego0, pair.classes,
                                               class_to_meta=options.class_to_meta, **common)
            self.buckets = buckets if self.buckets is None else self.buckets + buckets
        threeway = metrics.av2_bucket_stats(pair.pc0, flow, pair.flow, pair.ego1_from_ego0, pair.classes,
                                            class_to_meta=threeway_meta, edges=metrics.THREEWAY_EDGES,
                                            metas=("BACKGROUND", "FOREGROUND"), **common)
        self.threeway = threeway if self.threeway is None else self.threeway + threeway
        self.seconds.append(seconds)

    def summary(self) -> dict:
        """{"paper": {"point_weighted"|"per_pair": {category: row}}, "threeway", "bucketed", "seconds_per_pair"}."""
        out = {"paper": self.paper.table(), "pairs": len(self.seconds),
               "seconds_per_pair": float(np.median(self.seconds)) if self.seconds else math.nan}
        out["threeway"] = metrics.threeway_epe(self.threeway) if self.threeway is not None else None
        if self.buckets is not None:
            bucketed = metrics.bucketed_epe(self.buckets)
            out["bucketed"] = {"per_class": {k: {"static_epe": s, "dynamic_normalized_epe": d}
                                             for k, (s, d) in bucketed["per_class"].items()},
                               "mean": {"static_epe": bucketed["mean"][0],
                                        "dynamic_normalized_epe": bucketed["mean"][1]}}
        else:
            out["bucketed"] = None
        return out


@dataclass
class EvaluationResult:
    """Per-method summaries (see :meth:`MethodScores.summary`), the pairs scored and the ones skipped."""

    summaries: dict[str, dict]
    pairs: list[str]
    failures: list[dict]
    settings: dict


def evaluate(dataset, methods: dict[str, Method], options: MetricOptions, indices=None, horizon: int = 1,
             on_pair: Callable[[int, FramePair, dict[str, np.ndarray]], None] | None = None,
             progress: bool = False) -> EvaluationResult:
    """Score every method on ``dataset.pair(i, horizon)`` for i in ``indices`` (default: all).

    ``on_pair(position, pair, flows)`` is called after each scored pair (pictures); ``flows`` maps method -> full flow.
    """
    indices = list(range(len(dataset))) if indices is None else list(indices)
    scores = {name: MethodScores() for name in methods}
    done, failures = [], []
    iterator = indices
    if progress:
        from tqdm import tqdm

        iterator = tqdm(indices, desc="eval", unit="pair", file=sys.stderr)
    for index in iterator:
        try:
            pair = dataset.pair(index, horizon=horizon)
            if not pair.has_ground_truth or pair.classes is None:
                raise ValueError(f"{pair.source}: no ground-truth flow and classes to score against")
            flows, seconds = {}, {}
            for name, method in methods.items():
                start = time.perf_counter()
                flow = np.asarray(method(pair, index), np.float32)
                seconds[name] = time.perf_counter() - start
                if flow.shape != pair.pc0.shape:
                    raise ValueError(f"method {name} returned flow of shape {flow.shape} for pc0 {pair.pc0.shape}")
                flows[name] = flow
        except Exception as error:  # a bad sample is recorded and skipped for every method
            failures.append({"index": index, "sample_id": _safe_id(dataset, index),
                             "reason": f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"})
            continue
        for name, flow in flows.items():
            scores[name].add(pair, flow, seconds[name], options)
        done.append(pair.sample_id or _safe_id(dataset, index))
        if on_pair is not None:
            on_pair(len(done) - 1, pair, flows)
    settings = {"crop": options.crop, "include_ground": options.include_ground, "relative_to": options.relative_to,
                "dynamic_speed": options.dynamic_speed, "horizon": horizon,
                "bucketed_classes": options.class_to_meta is not None}
    return EvaluationResult({name: s.summary() for name, s in scores.items()}, done, failures, settings)


def _safe_id(dataset, index: int) -> str:
    try:
        return dataset.sample_id(index)
    except Exception:  # the id itself may be what is broken
        return f"#{index}"


# ---------------------------------------------------------------------------------------------------- output

PAPER_COLUMNS = ("EPE", "AccS", "AccR")
SPLITS = ("dynamic_fg", "static_fg", "static_bg")


def paper_table(result: EvaluationResult, weighting: str = "point_weighted") -> str:
    """The paper's layout: per method EPE / Acc-S / Acc-R of dynamic fg, static fg, static bg, and s per pair;
    then Threeway EPE and mean bucketed normalised EPE."""
    head = f"{'method':<10}" + "".join(f"| {s:^26} " for s in SPLITS) + "| s/pair | 3-way  | dyn.norm"
    sub = f"{'':<10}" + "| EPE(m)   Acc-S    Acc-R  " * len(SPLITS) + "|        |  EPE   |  EPE"
    lines = [head, sub]
    for name, summary in result.summaries.items():
        rows = summary["paper"][weighting]
        cells = "".join("| " + " ".join(f"{rows[s][c]:>8.4f}" for c in PAPER_COLUMNS) + " " for s in SPLITS)
        three = summary["threeway"]["threeway"] if summary["threeway"] else math.nan
        dyn = summary["bucketed"]["mean"]["dynamic_normalized_epe"] if summary["bucketed"] else math.nan
        lines.append(f"{name:<10}{cells}| {summary['seconds_per_pair']:6.3f} | {three:6.4f} | {dyn:6.4f}")
    return "\n".join(lines)


def csv_rows(result: EvaluationResult) -> list[dict]:
    """Flat rows: one per (method, weighting, category) with every paper column, then Threeway / bucketed rows."""
    rows = []
    for name, summary in result.summaries.items():
        for weighting, table in summary["paper"].items():
            for category, values in table.items():
                rows.append({"method": name, "metric": f"paper/{weighting}/{category}", **values})
        if summary["threeway"]:
            for key, value in summary["threeway"].items():
                rows.append({"method": name, "metric": f"threeway/{key}", "EPE": value})
        if summary["bucketed"]:
            for cls, values in summary["bucketed"]["per_class"].items():
                rows.append({"method": name, "metric": f"bucketed/{cls}", "EPE": values["static_epe"],
                             "dynamic_normalized_epe": values["dynamic_normalized_epe"]})
        rows.append({"method": name, "metric": "seconds_per_pair", "EPE": summary["seconds_per_pair"]})
    return rows


def write_results(result: EvaluationResult, out_dir, extra: dict | None = None) -> tuple[Path, Path]:
    """``metrics.json`` (everything, NaN as null) and ``metrics.csv`` under ``out_dir``, each written atomically."""
    from icpflow.shards.writer import write_text_atomic

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    document = {"methods": result.summaries, "pairs": result.pairs, "failures": result.failures,
                "settings": result.settings} | (extra or {})
    json_path, csv_path = out_dir / "metrics.json", out_dir / "metrics.csv"
    write_text_atomic(json_path, json.dumps(_nan_to_none(document), indent=2) + "\n")
    rows = csv_rows(result)
    columns = ["method", "metric", "EPE", "AccS", "AccR", "Outliers", "count", "dynamic_normalized_epe"]
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomic(csv_path, buffer.getvalue())
    return json_path, csv_path


def _nan_to_none(value):
    if isinstance(value, dict):
        return {k: _nan_to_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_nan_to_none(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


# ---------------------------------------------------------------------------------------------------- eval.py

def run_eval(cfg, progress: bool = True) -> int:
    """``eval.py``: evaluate ``cfg.method`` (a name or a list) on ``cfg.dataset`` / ``cfg.split``; print the table,
    write ``metrics.json``, ``metrics.csv`` and ``bev/<pair>_<method>.png`` under ``cfg.out_dir``.

    Returns the exit status: 0 scored, 1 some pairs failed (listed in metrics.json), 2 could not start.
    """
    from omegaconf import OmegaConf

    from icpflow.labelling.cli import open_dataset, teacher_config
    from icpflow.viz import plot_bev

    names = [cfg.method] if isinstance(cfg.method, str) else list(cfg.method)
    horizon = int(cfg.horizon)
    try:
        if not names or len(set(names)) != len(names):
            raise EvaluationError(f"method must name distinct methods, got {names}")
        dataset = open_dataset(cfg)
        if not 1 <= horizon <= getattr(dataset, "max_horizon", 1):
            raise EvaluationError(f"dataset {cfg.dataset.name}: horizon={horizon} outside 1..{dataset.max_horizon}")
        teacher = teacher_config(cfg) if "icpflow" in names else None
        methods = {name: build_method(name, dataset=dataset, teacher_config=teacher, horizon=horizon,
                                      tracker=bool(cfg.tracker), checkpoint=cfg.checkpoint, shards=cfg.shards)
                   for name in names}
    except (EvaluationError, ValueError, RuntimeError) as error:
        print(f"eval: {error}", file=sys.stderr)
        return 2
    options = MetricOptions(crop=None if cfg.crop is None else float(cfg.crop), include_ground=bool(cfg.include_ground),
                            relative_to=str(cfg.relative_to), class_to_meta=dataset.class_to_meta)
    out_dir = Path(cfg.out_dir)
    limit = len(dataset) if cfg.limit is None else min(int(cfg.limit), len(dataset))

    def pictures(position: int, pair: FramePair, flows: dict[str, np.ndarray]) -> None:
        if position < int(cfg.bev):
            stem = pair.sample_id.replace("/", "_") or f"pair{position:04d}"
            for name, flow in flows.items():
                plot_bev(pair, out_dir / "bev" / f"{stem}_{name}.png", predicted=flow, extent=float(cfg.bev_extent),
                         title=f"{cfg.dataset.name} {cfg.split} {pair.sample_id}: {name}")

    result = evaluate(dataset, methods, options, range(limit), horizon, on_pair=pictures, progress=progress)
    if not result.pairs:
        print(f"eval: no pair could be scored ({len(result.failures)} failed; first: "
              f"{result.failures[0]['reason'] if result.failures else 'none'})", file=sys.stderr)
        return 2
    extra = {"dataset": cfg.dataset.name, "split": cfg.split,
             "config": OmegaConf.to_container(cfg, resolve=True)}
    json_path, _ = write_results(result, out_dir, extra)
    weighting = "per_pair" if cfg.weighting == "per_pair" else "point_weighted"
    print(f"{cfg.dataset.name} {cfg.split}: {len(result.pairs)} pairs, horizon {horizon}, crop {options.crop} m, "
          f"{weighting.replace('_', '-')} (see {json_path} for both weightings)")
    print(paper_table(result, weighting))
    for failure in result.failures[:10]:
        print(f"  skipped {failure['sample_id']}: {failure['reason']}", file=sys.stderr)
    return 1 if result.failures else 0
