"""Evaluate scene-flow methods on a dataset with ground truth: one table, a row per method and frame gap
(``eval.py``).

- ``methods``: the methods by name (``zero``, ``ego``, ``icpflow``, ``shards``; others passed in as factories) and
  the frame gaps (``horizon=``);
- ``scoring``: each pair's point selection made once, every method's statistics on it, running sums per method;
- ``run``: the loop over samples, every gap on the same start scans, failures skipped for every method, per-pair
  hooks (pictures, a viewer), a partial result when stopped;
- ``report``: the printed table, ``metrics.json`` (one schema for one gap or several) and ``metrics.csv``, and
  their readers;
- ``cli``: ``eval.py``'s config to an exit status (one-line errors, out_dir checked first, SIGTERM and Ctrl-C keep
  the pairs scored).
"""

from icpflow.evaluation.cli import run_eval
from icpflow.evaluation.methods import METHODS, EvaluationError, Method, MethodFactory, build_methods, parse_horizons
from icpflow.evaluation.report import is_complete, method_summary, read_metrics, write_results
from icpflow.evaluation.run import Evaluation, EvaluationResult, PairHook, PairPredictions, evaluate
from icpflow.evaluation.scoring import MethodScores, MetricOptions, PairScorer

__all__ = [
    "METHODS",
    "Evaluation",
    "EvaluationError",
    "EvaluationResult",
    "Method",
    "MethodFactory",
    "MethodScores",
    "MetricOptions",
    "PairHook",
    "PairPredictions",
    "PairScorer",
    "build_methods",
    "evaluate",
    "is_complete",
    "method_summary",
    "parse_horizons",
    "read_metrics",
    "run_eval",
    "write_results",
]
