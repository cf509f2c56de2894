"""Evaluate scene-flow methods on a dataset with ground truth: one table, a row per method (``eval.py``).

A method is a callable ``method(pair, index) -> (N0, 3) float32 FULL flow`` (project convention, pc0's ego frame
of t -> positions in the ego frame of t + dt), built by :func:`build_methods` from its name; the teacher package's
own methods are built here:

- ``zero``: zero full flow; ``ego``: ego flow only (every point static in the world);
- ``icpflow``: the teacher (``conf/icpflow``), ``tracker=true`` chains it through intermediate frames
  (``tracker=[false,true]``: one row each, ``icpflow`` and ``icpflow+tracker``);
- ``shards``: the pseudo-labels a ``label.py`` run wrote (``shards=<out_dir>``), matched by sample id.

Other methods come in as factories by name (``run_eval(cfg, extra_methods={name: factory(cfg) -> method})``):
``eval.py`` adds ``student`` (``fastflow3d.eval_method``), so this package never imports the student.

Every method sees the same pairs; each pair's metric sums go into a :class:`MethodScores` (the paper's splits,
point-weighted and per pair; AV2 Threeway and bucketed normalised EPE; seconds per pair). A pair whose reading or
prediction raises is recorded in ``failures`` and skipped for every method, so all rows score the same pairs.

Long horizon (``horizon=[1,2,3,4]`` or ``horizon=1..4``): every method is scored on the pairs (t, t + k) of the
same start scans t for each k, one row per (method, k) with the mean real dt of those pairs (``horizon_rows``).
"""

from __future__ import annotations

import csv
import functools
import io
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from icpflow import metrics
from icpflow.baselines import ego_only_flow, zero_flow
from icpflow.datasets.base import sample_id_or_index
from icpflow.frames import FramePair
from icpflow.teacher.config import teacher_config  # importing it stores the icpflow schema eval.yaml composes with

METHODS = ("zero", "ego", "icpflow", "shards")
Method = Callable[[FramePair, int], np.ndarray]
#: a method from the run config (``eval.py``'s); raises :class:`EvaluationError` when the config does not allow it
MethodFactory = Callable[[Any], Method]


class EvaluationError(ValueError):
    """A one-line reason why the evaluation cannot start."""


# ---------------------------------------------------------------------------------------------------- methods


class TeacherMethod:
    """The ICP-Flow teacher (an ``ICPFlow``) on pairs (t, t + horizon), with the pair's own ego motion and ground
    masks when it has them; ``tracker``: chained through the intermediate frames."""

    def __init__(self, teacher, dataset, horizon: int = 1, tracker: bool = False):
        self.teacher, self.dataset, self.horizon, self.tracker = teacher, dataset, horizon, tracker

    def __call__(self, pair: FramePair, index: int) -> np.ndarray:
        if self.tracker and self.horizon > 1:
            from icpflow.teacher.tracker import sample_tracker_flow

            return sample_tracker_flow(self.teacher, self.dataset, index, self.horizon, pair).flow
        return self.teacher(
            pair.pc0,
            pair.pc1,
            ego1_from_ego0=pair.ego1_from_ego0,
            ground0=pair.ground0,
            ground1=pair.ground1,
            time0=pair.time0,
            time1=pair.time1,
            gap=self.horizon,
            dt=pair.dt,
        ).flow


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


def build_methods(
    names,
    horizons=(1,),
    trackers=(False,),
    *,
    dataset=None,
    teacher_config=None,
    shards=None,
    extra: dict[str, Callable[[], Method]] | None = None,
) -> dict[int, dict[str, Method]]:
    """Per horizon k, the methods scored on pairs (t, t + k) by row name, each ``method(pair, index) -> full flow``.

    ``icpflow`` gives one row per value of ``trackers``: ``icpflow``, and ``icpflow+tracker`` when both are asked
    for. At horizon 1 the tracker has nothing to chain: both rows are then the same object (called once per pair).
    The other methods, and the teacher's ``ICPFlow``, are built once and shared by every horizon. ``extra`` gives
    the methods of other packages by name, each built by calling it (no arguments).
    """
    extra = extra or {}
    names, trackers = list(names), list(trackers)
    if not names or len(set(names)) != len(names):
        raise EvaluationError(f"method must name distinct methods, got {names}")
    if not trackers or not all(isinstance(t, bool) for t in trackers) or len(set(trackers)) != len(trackers):
        raise EvaluationError(f"tracker must be true, false or [false,true], got {trackers}")
    shared = {}
    for name in names:
        if name == "zero":
            shared[name] = lambda pair, index: zero_flow(pair)
        elif name == "ego":
            shared[name] = lambda pair, index: ego_only_flow(pair)
        elif name == "icpflow":
            from icpflow.teacher import ICPFlow

            shared[name] = ICPFlow(teacher_config)
        elif name == "shards":
            if not shards:
                raise EvaluationError("method shards needs shards=<a label.py out_dir>")
            if len(horizons) > 1:
                raise EvaluationError("method shards scores the one horizon its labels were made for; give one horizon")
            shared[name] = ShardMethod(shards)
        elif name in extra:
            shared[name] = extra[name]()
        else:
            raise EvaluationError(f"unknown method {name!r}, expected one of {', '.join([*METHODS, *extra])}")
    methods = {}
    for horizon in horizons:
        row = {}
        for name in names:
            if name != "icpflow":
                row[name] = shared[name]
                continue
            direct = TeacherMethod(shared[name], dataset, horizon)
            for tracked in trackers:
                key = "icpflow+tracker" if tracked and len(trackers) > 1 else "icpflow"
                row[key] = TeacherMethod(shared[name], dataset, horizon, True) if tracked and horizon > 1 else direct
        methods[horizon] = row
    return methods


def parse_horizons(value) -> list[int]:
    """``horizon=`` as ascending distinct frame gaps: ``2``, ``[1,2,3,4]`` or ``"1..4"``."""
    try:
        if isinstance(value, str) and ".." in value:
            first, last = value.split("..")
            horizons = list(range(int(first), int(last) + 1))
        else:
            horizons = [int(value)] if isinstance(value, (int, str)) else [int(k) for k in value]
    except (TypeError, ValueError):
        raise EvaluationError(f"horizon must be an integer, a list or first..last, got {value!r}") from None
    if not horizons or min(horizons) < 1 or len(set(horizons)) != len(horizons):
        raise EvaluationError(f"horizon must list distinct frame gaps >= 1, got {value!r}")
    return sorted(horizons)


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
    dts: list[float] = field(default_factory=list)

    def add(self, pair: FramePair, flow: np.ndarray, seconds: float, options: MetricOptions) -> None:
        self.paper.add(
            metrics.frame_pair_stats(
                pair,
                flow,
                crop=options.crop,
                include_ground=options.include_ground,
                relative_to=options.relative_to,
                dynamic_speed=options.dynamic_speed,
            )
        )
        common = dict(ground=None if options.include_ground else pair.ground0, flow_valid=pair.flow_valid)
        threeway_meta = {0: "BACKGROUND"} | {int(c): "FOREGROUND" for c in np.unique(pair.classes) if c > 0}
        if options.class_to_meta is not None:
            threeway_meta = {
                c: "BACKGROUND" if m == "BACKGROUND" else "FOREGROUND" for c, m in options.class_to_meta.items()
            }
            buckets = metrics.av2_bucket_stats(
                pair.pc0,
                flow,
                pair.flow,
                pair.ego1_from_ego0,
                pair.classes,
                class_to_meta=options.class_to_meta,
                **common,
            )
            self.buckets = buckets if self.buckets is None else self.buckets + buckets
        threeway = metrics.av2_bucket_stats(
            pair.pc0,
            flow,
            pair.flow,
            pair.ego1_from_ego0,
            pair.classes,
            class_to_meta=threeway_meta,
            edges=metrics.THREEWAY_EDGES,
            metas=("BACKGROUND", "FOREGROUND"),
            **common,
        )
        self.threeway = threeway if self.threeway is None else self.threeway + threeway
        self.seconds.append(seconds)
        self.dts.append(float(pair.dt))

    def summary(self) -> dict:
        """{"paper": {"point_weighted"|"per_pair": {category: row}}, "threeway", "bucketed", "seconds_per_pair",
        "dt_s" (mean seconds between the scans of the pairs)}."""
        out = {
            "paper": self.paper.table(),
            "pairs": len(self.seconds),
            "seconds_per_pair": float(np.median(self.seconds)) if self.seconds else math.nan,
            "dt_s": float(np.mean(self.dts)) if self.dts else math.nan,
        }
        out["threeway"] = metrics.threeway_epe(self.threeway) if self.threeway is not None else None
        if self.buckets is not None:
            bucketed = metrics.bucketed_epe(self.buckets)
            out["bucketed"] = {
                "per_class": {
                    k: {"static_epe": s, "dynamic_normalized_epe": d} for k, (s, d) in bucketed["per_class"].items()
                },
                "mean": {"static_epe": bucketed["mean"][0], "dynamic_normalized_epe": bucketed["mean"][1]},
            }
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


def evaluate(
    dataset,
    methods: dict[str, Method],
    options: MetricOptions,
    indices=None,
    horizon: int = 1,
    on_pair: Callable[[int, int, FramePair, dict[str, np.ndarray]], None] | None = None,
    progress: bool = False,
) -> EvaluationResult:
    """Score every method on ``dataset.pair(i, horizon)`` for i in ``indices`` (default: all); see
    :func:`evaluate_horizons`."""
    return evaluate_horizons(dataset, {horizon: methods}, options, indices, on_pair, progress)[horizon]


def evaluate_horizons(
    dataset,
    methods: dict[int, dict[str, Method]],
    options: MetricOptions,
    indices=None,
    on_pair: Callable[[int, int, FramePair, dict[str, np.ndarray]], None] | None = None,
    progress: bool = False,
) -> dict[int, EvaluationResult]:
    """Score ``methods[k]`` on ``dataset.pair(i, horizon=k)`` for every k and i in ``indices`` (default: all).

    A sample whose pair cannot be read or predicted at any k is skipped at every k, so all rows score the same
    start scans. A method object listed under several names is called once per pair. ``on_pair(position, k,
    pair, flows)`` is called after each scored pair (pictures); ``flows`` maps method -> (N0, 3) full flow.
    """
    indices = list(range(len(dataset))) if indices is None else list(indices)
    scores = {k: {name: MethodScores() for name in row} for k, row in methods.items()}
    done, failures = {k: [] for k in methods}, []
    iterator = indices
    if progress:
        from tqdm import tqdm

        iterator = tqdm(indices, desc="eval", unit="sample", file=sys.stderr)
    for index in iterator:
        scored = []
        for horizon, row in methods.items():
            try:
                scored.append((horizon, *_predict(dataset, index, horizon, row)))
            except Exception as error:  # a bad sample is recorded and skipped for every method and horizon
                failures.append(
                    {
                        "index": index,
                        "sample_id": sample_id_or_index(dataset, index),
                        "horizon": horizon,
                        "reason": f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}",
                    }
                )
                break
        else:
            for horizon, pair, flows, seconds in scored:
                for name, flow in flows.items():
                    scores[horizon][name].add(pair, flow, seconds[name], options)
                done[horizon].append(pair.sample_id or sample_id_or_index(dataset, index))
                if on_pair is not None:
                    on_pair(len(done[horizon]) - 1, horizon, pair, flows)
    settings = {
        "crop": options.crop,
        "include_ground": options.include_ground,
        "relative_to": options.relative_to,
        "dynamic_speed": options.dynamic_speed,
        "bucketed_classes": options.class_to_meta is not None,
    }
    return {
        k: EvaluationResult(
            {name: s.summary() for name, s in scores[k].items()}, done[k], failures, settings | {"horizon": k}
        )
        for k in methods
    }


def _predict(dataset, index: int, horizon: int, methods: dict[str, Method]):
    """``(pair, flows, seconds)`` of every method on ``dataset.pair(index, horizon)``; raises what breaks."""
    pair = dataset.pair(index, horizon=horizon)
    if not pair.has_ground_truth or pair.classes is None:
        raise ValueError(f"{pair.source}: no ground-truth flow and classes to score against")
    flows, seconds, by_object = {}, {}, {}
    for name, method in methods.items():
        if id(method) not in by_object:
            start = time.perf_counter()
            flow = np.asarray(method(pair, index), np.float32)
            by_object[id(method)] = flow, time.perf_counter() - start
            if flow.shape != pair.pc0.shape:
                raise ValueError(f"method {name} returned flow of shape {flow.shape} for pc0 {pair.pc0.shape}")
        flows[name], seconds[name] = by_object[id(method)]
    return pair, flows, seconds


# ---------------------------------------------------------------------------------------------------- output

PAPER_COLUMNS = ("EPE", "AccS", "AccR")
SPLITS = ("dynamic_fg", "static_fg", "static_bg")
HORIZON_COLUMNS = (
    "method",
    "horizon",
    "dt_s",
    *(f"EPE_{c}" for c in metrics.CATEGORIES),
    "threeway_EPE",
    "seconds_per_pair",
    "pairs",
)


def paper_table(result: EvaluationResult, weighting: str = "point_weighted") -> str:
    """The paper's layout: per method EPE / Acc-S / Acc-R of dynamic fg, static fg, static bg, and s per pair;
    then Threeway EPE and mean bucketed normalised EPE."""
    width = max(10, *(len(name) + 1 for name in result.summaries))
    head = f"{'method':<{width}}" + "".join(f"| {s:^26} " for s in SPLITS) + "| s/pair | 3-way  | dyn.norm"
    sub = f"{'':<{width}}" + "| EPE(m)   Acc-S    Acc-R  " * len(SPLITS) + "|        |  EPE   |  EPE"
    lines = [head, sub]
    for name, summary in result.summaries.items():
        rows = summary["paper"][weighting]
        cells = "".join("| " + " ".join(f"{rows[s][c]:>8.4f}" for c in PAPER_COLUMNS) + " " for s in SPLITS)
        three = summary["threeway"]["threeway"] if summary["threeway"] else math.nan
        dyn = summary["bucketed"]["mean"]["dynamic_normalized_epe"] if summary["bucketed"] else math.nan
        lines.append(f"{name:<{width}}{cells}| {summary['seconds_per_pair']:6.3f} | {three:6.4f} | {dyn:6.4f}")
    return "\n".join(lines)


def horizon_rows(results: dict[int, EvaluationResult], weighting: str = "point_weighted") -> list[dict]:
    """The long-horizon table: one row per (method, horizon k), methods in order, k ascending, with the mean real
    dt (s) of the pairs, the EPE (m) of each category (``metrics.CATEGORIES``), Threeway EPE and s per pair."""
    first = results[min(results)]
    rows = []
    for name in first.summaries:
        for horizon in sorted(results):
            summary = results[horizon].summaries[name]
            table = summary["paper"][weighting]
            rows.append(
                {
                    "method": name,
                    "horizon": horizon,
                    "dt_s": summary["dt_s"],
                    **{f"EPE_{c}": table[c]["EPE"] for c in metrics.CATEGORIES},
                    "threeway_EPE": summary["threeway"]["threeway"] if summary["threeway"] else math.nan,
                    "seconds_per_pair": summary["seconds_per_pair"],
                    "pairs": summary["pairs"],
                }
            )
    return rows


def horizon_table(rows: list[dict]) -> str:
    """:func:`horizon_rows` as text: EPE (m) against the time gap."""
    width = max(10, *(len(row["method"]) + 1 for row in rows))
    lines = [
        f"{'method':<{width}}| k | dt (s) |"
        + "".join(f" {c:>10} |" for c in metrics.CATEGORIES)
        + " 3-way EPE | s/pair",
        f"{'':<{width}}|   |        |" + "".join(f" {'EPE (m)':>10} |" for _ in metrics.CATEGORIES) + "           |",
    ]
    for row in rows:
        lines.append(
            f"{row['method']:<{width}}| {row['horizon']} | {row['dt_s']:6.3f} |"
            + "".join(f" {row[f'EPE_{c}']:>10.4f} |" for c in metrics.CATEGORIES)
            + f" {row['threeway_EPE']:>9.4f} | {row['seconds_per_pair']:6.3f}"
        )
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
                rows.append(
                    {
                        "method": name,
                        "metric": f"bucketed/{cls}",
                        "EPE": values["static_epe"],
                        "dynamic_normalized_epe": values["dynamic_normalized_epe"],
                    }
                )
        rows.append({"method": name, "metric": "seconds_per_pair", "EPE": summary["seconds_per_pair"]})
    return rows


def write_results(result: EvaluationResult, out_dir, extra: dict | None = None) -> tuple[Path, Path]:
    """``metrics.json`` (everything, NaN as null) and ``metrics.csv`` under ``out_dir``, each written atomically."""
    document = {
        "methods": result.summaries,
        "pairs": result.pairs,
        "failures": result.failures,
        "settings": result.settings,
    } | (extra or {})
    columns = ["method", "metric", "EPE", "AccS", "AccR", "Outliers", "count", "dynamic_normalized_epe"]
    return _write_json_csv(out_dir, document, csv_rows(result), columns)


def write_horizon_results(
    results: dict[int, EvaluationResult], out_dir, weighting: str = "point_weighted", extra: dict | None = None
) -> tuple[Path, Path]:
    """Long horizon: ``metrics.json`` (the table, every summary as ``methods[name][k]``, the pairs per k, the
    failures) and ``metrics.csv`` (the table, one row per (method, k)) under ``out_dir``, written atomically."""
    first = results[min(results)]
    settings = {key: value for key, value in first.settings.items() if key != "horizon"}
    rows = horizon_rows(results, weighting)
    document = {
        "horizons": sorted(results),
        "table": {"weighting": weighting, "rows": rows},
        "methods": {name: {str(k): results[k].summaries[name] for k in sorted(results)} for name in first.summaries},
        "pairs": {str(k): results[k].pairs for k in sorted(results)},
        "failures": first.failures,
        "settings": settings | {"horizons": sorted(results)},
    } | (extra or {})
    return _write_json_csv(out_dir, document, rows, list(HORIZON_COLUMNS))


def _write_json_csv(out_dir, document: dict, rows: list[dict], columns: list[str]) -> tuple[Path, Path]:
    from icpflow.atomic import write_text_atomic

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    json_path, csv_path = out_dir / "metrics.json", out_dir / "metrics.csv"
    write_text_atomic(json_path, json.dumps(_nan_to_none(document), indent=2) + "\n")
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


def run_eval(cfg, progress: bool = True, extra_methods: dict[str, MethodFactory] | None = None) -> int:
    """``eval.py``: evaluate ``cfg.method`` (a name or a list) on ``cfg.dataset`` / ``cfg.split`` at ``cfg.horizon``
    (a gap or several); print the table, write ``metrics.json`` and ``metrics.csv`` under ``cfg.out_dir``, with
    ``bev/`` (matplotlib) and ``render/`` (open3d) pictures ``<pair>_<method>.png`` (under ``k<gap>/`` when several
    gaps are scored).

    ``extra_methods``: methods of other packages by name, each ``factory(cfg) -> method`` (``eval.py`` gives
    ``student``). Returns the exit status: 0 scored, 1 some pairs failed (listed in metrics.json), 2 could not start.
    """
    from omegaconf import OmegaConf

    from icpflow.datasets.from_config import open_dataset
    from icpflow.viz import offscreen_problem, plot_bev, render_pair

    names = list(cfg.method) if OmegaConf.is_list(cfg.method) else [cfg.method]
    trackers = list(cfg.tracker) if OmegaConf.is_list(cfg.tracker) else [cfg.tracker]
    try:
        horizons = parse_horizons(cfg.horizon)
        dataset = open_dataset(cfg, horizons[-1])
        teacher = teacher_config(cfg) if "icpflow" in names else None
        if teacher is not None and horizons[-1] > teacher.pairing.max_frame_gap:
            raise EvaluationError(
                f"icpflow: horizon={horizons[-1]} exceeds the teacher's max_frame_gap "
                f"{teacher.pairing.max_frame_gap} (icpflow.pairing.max_frame_gap=...)"
            )
        problem = offscreen_problem() if int(cfg.render) > 0 else None
        if problem:
            raise EvaluationError(f"render={cfg.render}: {problem}")
        extra = {name: functools.partial(factory, cfg) for name, factory in (extra_methods or {}).items()}
        methods = build_methods(
            names, horizons, trackers, dataset=dataset, teacher_config=teacher, shards=cfg.shards, extra=extra
        )
    except (EvaluationError, ValueError, RuntimeError) as error:
        print(f"eval: {error}", file=sys.stderr)
        return 2
    options = MetricOptions(
        crop=None if cfg.crop is None else float(cfg.crop),
        include_ground=bool(cfg.include_ground),
        relative_to=str(cfg.relative_to),
        class_to_meta=dataset.class_to_meta,
    )
    out_dir = Path(cfg.out_dir)
    limit = len(dataset) if cfg.limit is None else min(int(cfg.limit), len(dataset))
    long_horizon = len(horizons) > 1

    def pictures(position: int, horizon: int, pair: FramePair, flows: dict[str, np.ndarray]) -> None:
        stem = pair.sample_id.replace("/", "_") or f"pair{position:04d}"
        sub = f"k{horizon}" if long_horizon else ""
        for name, flow in flows.items():
            if position < int(cfg.bev):
                plot_bev(
                    pair,
                    out_dir / "bev" / sub / f"{stem}_{name}.png",
                    predicted=flow,
                    extent=float(cfg.bev_extent),
                    title=f"{cfg.dataset.name} {cfg.split} {pair.sample_id}: {name}",
                )
            if position < int(cfg.render):
                render_pair(
                    pair,
                    out_dir / "render" / sub / f"{stem}_{name}.png",
                    predicted=flow,
                    size=tuple(cfg.render_size),
                    extent=float(cfg.bev_extent),
                )

    results = evaluate_horizons(dataset, methods, options, range(limit), on_pair=pictures, progress=progress)
    first = results[horizons[0]]
    if not first.pairs:
        print(
            f"eval: no pair could be scored ({len(first.failures)} failed; first: "
            f"{first.failures[0]['reason'] if first.failures else 'none'})",
            file=sys.stderr,
        )
        return 2
    extra = {"dataset": cfg.dataset.name, "split": cfg.split, "config": OmegaConf.to_container(cfg, resolve=True)}
    weighting = "per_pair" if cfg.weighting == "per_pair" else "point_weighted"
    if long_horizon:
        json_path, _ = write_horizon_results(results, out_dir, weighting, extra)
        print(
            f"{cfg.dataset.name} {cfg.split}: {len(first.pairs)} start scans, horizons "
            f"{', '.join(map(str, horizons))}, crop {options.crop} m, {weighting.replace('_', '-')} "
            f"(see {json_path} for both weightings)"
        )
        print(horizon_table(horizon_rows(results, weighting)))
    else:
        json_path, _ = write_results(first, out_dir, extra)
        print(
            f"{cfg.dataset.name} {cfg.split}: {len(first.pairs)} pairs, horizon {horizons[0]}, crop {options.crop} "
            f"m, {weighting.replace('_', '-')} (see {json_path} for both weightings)"
        )
        print(paper_table(first, weighting))
    for failure in first.failures[:10]:
        print(f"  skipped {failure['sample_id']}: {failure['reason']}", file=sys.stderr)
    return 1 if first.failures else 0
