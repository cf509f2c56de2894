"""The evaluation loop: every method at every frame gap on the same start scans, one path for one gap or several.

``methods[k]`` (see ``methods.build_methods``) is scored on ``dataset.pair(i, horizon=k)`` for every k and sample i.
A sample whose pair cannot be read, scored or predicted at any k is recorded in ``failures`` and skipped at every k
for every method, so all rows score the same start scans. A method object listed under several names is called
once per pair.

Per-pair hooks (BEV pictures, renders, a viewer) get every method's prediction of each scored pair as a
:class:`PairPredictions`; a hook that cannot write its file (disk full, no permission) is reported in one line and
dropped, the scoring goes on.

The loop can be stopped at any point (SIGTERM or Ctrl-C, turned into ``icpflow.core.errors_and_signals.Stop`` by
``eval.py``, or a bare ``KeyboardInterrupt``): the pairs scored so far stay consistent (a pair is added to every method
and gap at once, with the signals held), and :meth:`Evaluation.result` gives a partial result that says why it stopped.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from icpflow.core.atomic import WriteError
from icpflow.core.errors_and_signals import signals_held
from icpflow.core.frame_pair import FramePair
from icpflow.core.stops import raise_stop_behind
from icpflow.datasets.base import sample_id_or_index
from icpflow.evaluation.methods import Method
from icpflow.evaluation.scoring import MethodScores, MetricOptions, PairScorer, PairScores


@dataclass(frozen=True)
class PairPredictions:
    """One scored pair as the per-pair hooks see it: ``position`` (0 for the first pair scored at this gap),
    ``horizon`` k, the dataset ``index``, the ``pair`` (t, t + k), every method's FULL flow (N0, 3) float32 by row
    name and the seconds each took."""

    position: int
    horizon: int
    index: int
    pair: FramePair
    flows: dict[str, np.ndarray]
    seconds: dict[str, float]


#: a per-pair hook: pictures, renders, a viewer (called after the pair is scored)
PairHook = Callable[[PairPredictions], None]


@dataclass
class EvaluationResult:
    """Every method's summary per gap (``summaries[name][k]``, see ``MethodScores.summary``), the pairs scored per
    gap, the samples skipped, the settings, and ``stopped``: None when every sample was tried, else why the run
    stopped early (the result then covers only the pairs scored until then)."""

    horizons: list[int]
    summaries: dict[str, dict[int, dict]]
    pairs: dict[int, list[str]]
    failures: list[dict]
    settings: dict
    stopped: str | None = None

    @property
    def complete(self) -> bool:
        return self.stopped is None


class Evaluation:
    """The running state of one evaluation (see the module docstring); :meth:`run` scores, :meth:`result` sums up,
    also after an interruption."""

    def __init__(self, dataset, methods: dict[int, dict[str, Method]], options: MetricOptions):
        self.dataset, self.methods, self.options = dataset, methods, options
        self.scores = {k: {name: MethodScores() for name in row} for k, row in methods.items()}
        self.done: dict[int, list[str]] = {k: [] for k in methods}
        self.failures: list[dict] = []

    def run(self, indices=None, hooks: Sequence[PairHook] = (), progress: bool = False) -> None:
        """Score every method on the samples ``indices`` (default: all), calling ``hooks`` after each scored pair."""
        indices = list(range(len(self.dataset))) if indices is None else list(indices)
        hooks = list(hooks)
        iterator = indices
        if progress:
            from icpflow.core.console import Progress

            iterator = Progress(indices, desc="eval", unit="sample")
        for index in iterator:
            scored = self._score_sample(index)
            if scored is None:
                continue
            with signals_held():
                for horizon, predictions, pair_scores in scored:
                    for name, scores in pair_scores.items():
                        self.scores[horizon][name].add(scores)
                    self.done[horizon].append(predictions.pair.sample_id or sample_id_or_index(self.dataset, index))
            for _, predictions, _ in scored:
                for hook in list(hooks):
                    try:
                        hook(predictions)
                    except WriteError as error:  # the pictures are not worth the scores: go on without them
                        print(f"eval: {error}; no more files from {_hook_name(hook)}", file=sys.stderr)
                        hooks.remove(hook)

    def _score_sample(self, index: int) -> list[tuple[int, PairPredictions, dict[str, PairScores]]] | None:
        """Every gap of sample ``index`` predicted and scored, or None (recorded in ``failures``)."""
        scored = []
        for horizon, row in self.methods.items():
            try:
                pair = self.dataset.pair(index, horizon=horizon)
                scorer = PairScorer(pair, self.options)
                flows, seconds = _predict(pair, index, row)
                pair_scores = {name: scorer.score(flows[name], seconds[name]) for name in row}
            except Exception as error:  # a bad sample is recorded and skipped for every method and horizon
                raise_stop_behind(error)
                message = str(error).splitlines()[0] if str(error) else ""
                self.failures.append(
                    {
                        "index": index,
                        "sample_id": sample_id_or_index(self.dataset, index),
                        "horizon": horizon,
                        "reason": f"{type(error).__name__}: {message}",
                    }
                )
                return None
            position = len(self.done[horizon])
            scored.append((horizon, PairPredictions(position, horizon, index, pair, flows, seconds), pair_scores))
        return scored

    def result(self, stopped: str | None = None) -> EvaluationResult:
        """The summaries of the pairs scored so far; ``stopped``: why the run ended early (None: it did not)."""
        horizons = sorted(self.methods)
        names = list(self.methods[horizons[0]])
        return EvaluationResult(
            horizons,
            {name: {k: self.scores[k][name].summary() for k in horizons} for name in names},
            {k: list(self.done[k]) for k in horizons},
            list(self.failures),
            self.options.settings() | {"horizons": horizons},
            stopped,
        )


def evaluate(
    dataset,
    methods: dict[int, dict[str, Method]],
    options: MetricOptions,
    indices=None,
    hooks: Sequence[PairHook] = (),
    progress: bool = False,
) -> EvaluationResult:
    """Score ``methods[k]`` on ``dataset.pair(i, horizon=k)`` for every k and i in ``indices`` (default: all)."""
    evaluation = Evaluation(dataset, methods, options)
    evaluation.run(indices, hooks, progress)
    return evaluation.result()


def _predict(pair: FramePair, index: int, methods: dict[str, Method]):
    """``(flows, seconds)`` of every method on ``pair``; raises what breaks."""
    flows, seconds, by_object = {}, {}, {}
    for name, method in methods.items():
        if id(method) not in by_object:
            start = time.perf_counter()
            flow = np.asarray(method(pair, index), np.float32)
            by_object[id(method)] = flow, time.perf_counter() - start
            if flow.shape != pair.pc0.shape:
                raise ValueError(f"method {name} returned flow of shape {flow.shape} for pc0 {pair.pc0.shape}")
        flows[name], seconds[name] = by_object[id(method)]
    return flows, seconds


def _hook_name(hook) -> str:
    return getattr(hook, "name", getattr(hook, "__name__", type(hook).__name__))
