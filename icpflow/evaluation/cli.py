"""``eval.py``: from the Hydra config (``conf/eval.yaml``) to an evaluation, its report and an exit status; :func:`main`
is the entry point with the methods of other packages (``fastflow3d-eval`` and ``eval.py`` add the student's).

Exit status: 0 every pair scored; 1 some pairs skipped (listed in metrics.json); 2 the run could not start (a bad
option or file, an ``out_dir`` that cannot be written, checked before the long work) or its results could not be
written (they are then saved in the system's temporary folder, and the table is printed); 130 Ctrl-C, 143 SIGTERM:
the pairs scored until then are written as a partial ``metrics.json`` (``"complete": false``) and no process of the
run is left. Every error is one line on stderr, naming the option or file.
"""

from __future__ import annotations

import contextlib
import functools
import multiprocessing
import os
import signal
import sys
import tempfile
import time
from pathlib import Path

from omegaconf import DictConfig

from icpflow.core.atomic import WriteError, write_text_atomic
from icpflow.core.console import quiet
from icpflow.core.entry_points import hydra_entry
from icpflow.core.errors_and_signals import (
    STOPS,
    one_line,
    reported,
    signals_held,
    stop_on_signals,
    stop_signum,
    stopped_by,
)
from icpflow.core.settings import check_config
from icpflow.evaluation.methods import EvaluationError, MethodFactory, build_methods, parse_horizons
from icpflow.evaluation.options import register
from icpflow.evaluation.report import check_writable, format_table, metrics_json, table_rows, write_results
from icpflow.evaluation.run import Evaluation, PairHook, PairPredictions
from icpflow.evaluation.scoring import MetricOptions
from icpflow.teacher.config import teacher_config

#: skipped samples listed at the end of a run (the rest: metrics.json)
SHOWN_FAILURES = 10


def end_child_processes() -> None:
    """End the helper processes a library started for this run (a multiprocessing or joblib pool), which would
    otherwise outlive it with their resource trackers: SIGTERM, then SIGKILL for one still there after 5 s (a
    process forked from this one ignores SIGTERM, ``icpflow.core.errors_and_signals.on_signals``)."""
    for child in multiprocessing.active_children():
        child.terminate()
    for child in multiprocessing.active_children():
        child.join(timeout=5)
        if child.is_alive():
            child.kill()
            child.join(timeout=5)


def picture_hooks(cfg, out_dir: Path, horizons: list[int]) -> list[PairHook]:
    """The per-pair hooks of ``cfg``: ``bev=N`` matplotlib BEV pictures and ``render=N`` open3d renders of the first
    N pairs, ``<pair>_<method>.png`` under ``bev/`` and ``render/`` (under ``k<gap>/`` when several gaps are
    scored). Other per-pair consumers (a viewer) are added to this list."""
    from icpflow.viz.pictures import plot_bev, render_pair

    def pictures(kind: str, count: int, draw) -> PairHook:
        """``draw(pair, path, flow)`` of every method's flow for the first ``count`` pairs, into ``kind/``."""

        def hook(predictions: PairPredictions) -> None:
            if predictions.position >= count:
                return
            folder = out_dir / kind / (f"k{predictions.horizon}" if len(horizons) > 1 else "")
            stem = predictions.pair.sample_id.replace("/", "_") or f"pair{predictions.position:04d}"
            for name, flow in predictions.flows.items():
                draw(predictions.pair, folder / f"{stem}_{name}.png", flow, name)

        hook.name = kind
        return hook

    def bev(pair, path, flow, name):
        title = f"{cfg.dataset.name} {cfg.split} {pair.sample_id}: {name}"
        plot_bev(pair, path, predicted=flow, extent=float(cfg.bev_extent), title=title)

    def render(pair, path, flow, name):
        render_pair(pair, path, predicted=flow, size=tuple(cfg.render_size), extent=float(cfg.bev_extent))

    return [pictures(kind, cfg[kind], draw) for kind, draw in (("bev", bev), ("render", render)) if cfg[kind]]


def recording_hook(recording, count: int, per_gap: bool) -> PairHook:
    """A per-pair hook logging the first ``count`` pairs (every method) into the rerun ``recording``
    (``icpflow.viz.recording.PairRecording``), under ``k<gap>/`` when several gaps are scored."""

    def hook(predictions: PairPredictions) -> None:
        if predictions.position < count:
            prefix = f"k{predictions.horizon}" if per_gap else ""
            recording.log_pair(predictions.position, predictions.pair, predictions.flows, prefix=prefix)

    hook.name = "viewer"
    return hook


def run_eval(
    cfg,
    progress: bool = True,
    extra_methods: dict[str, MethodFactory] | None = None,
    hooks: list[PairHook] | None = None,
) -> int:
    """``eval.py``: evaluate ``cfg.method`` (a name or a list) on ``cfg.dataset`` / ``cfg.split`` at ``cfg.horizon``
    (a gap or several); print the table, write ``metrics.json`` and ``metrics.csv`` under ``cfg.out_dir`` and the
    pictures of :func:`picture_hooks`.

    ``extra_methods``: methods of other packages by name, each ``factory(cfg) -> method`` (``eval.py`` gives
    ``student``); ``hooks``: more per-pair hooks. Returns the exit status (see the module docstring).
    """
    with stop_on_signals():  # SIGTERM and Ctrl-C raise icpflow.core.errors_and_signals.Stop
        try:
            return _run_eval(cfg, progress, extra_methods, hooks)
        except STOPS as caught:  # before the scoring began: nothing to keep
            stop = stopped_by(caught)
            end_child_processes()
            what, status = _stopped(stop)
            print(f"eval: {what} before any pair was scored; nothing written", file=sys.stderr)
            return status


def _stopped(stop: BaseException) -> tuple[str, int]:
    """What stopped the run (a :class:`Stop` or a bare KeyboardInterrupt), and its exit status."""
    signum = stop_signum(stop)
    return ("terminated (SIGTERM)" if signum == signal.SIGTERM else "interrupted (Ctrl-C)"), 128 + signum


def _run_eval(cfg, progress, extra_methods, hooks) -> int:
    from omegaconf import OmegaConf

    from icpflow.datasets.from_config import open_dataset
    from icpflow.viz.pictures import offscreen_problem
    from icpflow.viz.recording import PairRecording, check_viewer

    names = list(cfg.method) if OmegaConf.is_list(cfg.method) else [cfg.method]
    trackers = list(cfg.tracker) if OmegaConf.is_list(cfg.tracker) else [cfg.tracker]
    out_dir = Path(cfg.out_dir)
    try:
        check_config(cfg)  # the schema's rules (icpflow.evaluation.options.EvalOptions)
        horizons = parse_horizons(cfg.horizon)
        dataset = open_dataset(cfg, horizons[-1])
        # the eval's teacher settings for either teacher row (icpflow-raw alone had run the defaults)
        teacher = teacher_config(cfg) if {"icpflow", "icpflow-raw"} & set(names) else None
        if teacher is not None and horizons[-1] > teacher.pairing.max_frame_gap:
            raise EvaluationError(
                f"icpflow: horizon={horizons[-1]} exceeds the teacher's max_frame_gap "
                f"{teacher.pairing.max_frame_gap} (icpflow.pairing.max_frame_gap=...)"
            )
        viewer = check_viewer(cfg.get("viewer"))  # the 3D recording (icpflow.viz.recording)
        problem = offscreen_problem() if cfg.render > 0 else None
        if problem:
            raise EvaluationError(f"render={cfg.render}: {problem}")
        extra = {name: functools.partial(factory, cfg) for name, factory in (extra_methods or {}).items()}
        methods = build_methods(
            names, horizons, trackers, dataset=dataset, teacher_config=teacher, shards=cfg.shards, extra=extra
        )
        check_writable(out_dir)
    except WriteError as error:
        print(f"eval: {error}; nothing was scored: choose a writable out_dir=... with free space", file=sys.stderr)
        return 2
    except (EvaluationError, ValueError, RuntimeError, OSError) as error:
        print(f"eval: {one_line(error)}", file=sys.stderr)
        return 2
    metric_options = MetricOptions(
        crop=None if cfg.crop is None else float(cfg.crop),
        include_ground=cfg.include_ground,
        relative_to=str(cfg.relative_to),
        class_to_meta=dataset.class_to_meta,
    )
    limit = len(dataset) if cfg.limit is None else min(cfg.limit, len(dataset))
    evaluation = Evaluation(dataset, methods, metric_options)
    stopped, status = None, None
    recording = PairRecording(out_dir / "recording.rrd") if viewer else None
    all_hooks = [*picture_hooks(cfg, out_dir, horizons), *(hooks or [])]
    if recording is not None:
        all_hooks.append(recording_hook(recording, int(cfg.viewer_pairs), len(horizons) > 1))
    with recording or contextlib.nullcontext():
        try:
            evaluation.run(range(limit), all_hooks, progress)
        except STOPS as caught:  # SIGTERM or Ctrl-C (also inside a kernel): keep what was scored
            stopped, status = _stopped(stopped_by(caught))
            end_child_processes()
    if recording is not None:
        print(f"eval: 3D recording of {recording.pairs} pairs -> {recording.path} (open it with: rerun <file>)")
    result = evaluation.result(stopped)
    first = result.horizons[0]
    if not result.pairs[first] and stopped is None:
        reason = result.failures[0]["reason"] if result.failures else "none"
        print(f"eval: no pair could be scored ({len(result.failures)} failed; first: {reason})", file=sys.stderr)
        return 2
    extra = {"dataset": cfg.dataset.name, "split": cfg.split, "config": OmegaConf.to_container(cfg, resolve=True)}
    # what a method says it runs (its ``description``: a student's network precision and engine), under the table
    described = {name: method.description for name, method in methods[first].items() if hasattr(method, "description")}
    if described:
        extra["method_descriptions"] = described
    weighting = str(cfg.weighting)
    if result.pairs[first]:
        print(
            f"{cfg.dataset.name} {cfg.split}: {len(result.pairs[first])} pairs"
            f"{' (partial: ' + stopped + ')' if stopped else ''}, horizon{'s' if len(horizons) > 1 else ''} "
            f"{', '.join(map(str, horizons))}, crop {metric_options.crop} m, {weighting.replace('_', '-')}"
        )
        print(format_table(table_rows(result, weighting)))
        for name, description in described.items():
            print(f"  {name}: {description}")
    try:
        with signals_held():  # a second signal waits for the files
            json_path, _ = write_results(result, out_dir, weighting, extra)
    except WriteError as error:
        print(f"eval: {error}; {_save_elsewhere(result, weighting, extra)}", file=sys.stderr)
        return 2
    for failure in result.failures[:SHOWN_FAILURES]:
        print(f"  skipped {failure['sample_id']}: {failure['reason']}", file=sys.stderr)
    if len(result.failures) > SHOWN_FAILURES:
        print(f"  ... and {len(result.failures) - SHOWN_FAILURES} more (all in {json_path})", file=sys.stderr)
    if stopped:
        print(
            f"eval: {stopped}; the {len(result.pairs[first])} pairs scored are kept in {json_path} "
            '("complete": false); rerun the same command for all pairs',
            file=sys.stderr,
        )
        return status
    print(f"eval: -> {json_path} (both weightings, every split, per-class bucketed EPE)")
    return 1 if result.failures else 0


def _save_elsewhere(result, weighting: str, extra: dict) -> str:
    """Write the metrics.json that could not be written into the system's temporary folder; says where (or that
    only the printed table is left)."""
    path = Path(tempfile.gettempdir()) / f"eval-metrics-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}.json"
    try:
        write_text_atomic(path, metrics_json(result, weighting, extra))
    except WriteError as error:
        return f"nor in {path.parent} ({one_line(error)}); the table above holds the scores"
    return f"the scores were saved to {path} instead; free space or choose another out_dir=... and rerun"


def evaluation_task(extra_methods: dict[str, MethodFactory] | None = None):
    """The Hydra task of :func:`main`: :func:`run_eval` with ``extra_methods``, exiting with its status."""

    def task(cfg: DictConfig) -> None:
        quiet()
        with reported("eval"):
            status = run_eval(cfg, extra_methods=extra_methods)
            if status:
                sys.exit(status)

    return task


def main(extra_methods: dict[str, MethodFactory] | None = None) -> None:
    """Evaluate as ``conf/eval.yaml`` and the command line say, with this package's methods and ``extra_methods``
    (``fastflow3d.inference.eval_cli.main``, ``fastflow3d-eval``, adds the student's)."""
    register()  # eval_schema in Hydra's ConfigStore: the structured config conf/eval.yaml extends
    hydra_entry("eval", "eval", evaluation_task(extra_methods))
