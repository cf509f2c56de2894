"""Evaluate scene-flow methods on a dataset with ground truth: one table, a row per method and frame gap
(``eval.py``).

- ``methods``: the methods by name (``zero``, ``ego``, ``icpflow``, ``shards``; others passed in as factories) and
  the frame gaps (``horizon=``);
- ``metrics``: the scores themselves (the ICP-Flow paper's splits, Argoverse 2's Threeway and bucketed EPE), and
  ``baselines``: the trivial methods;
- ``options``: ``eval.py``'s structured config;
- ``scoring``: each pair's point selection made once, every method's statistics on it, running sums per method;
- ``run``: the loop over samples, every gap on the same start scans, failures skipped for every method, per-pair
  hooks (pictures, a viewer), a partial result when stopped;
- ``report``: the printed table, ``metrics.json`` (one schema for one gap or several) and ``metrics.csv``, and
  their readers;
- ``cli``: ``eval.py``'s config to an exit status (one-line errors, out_dir checked first, SIGTERM and Ctrl-C keep
  the pairs scored).
"""

#: the package's names -> the module that defines them, imported on first use: ``icpflow.evaluation.metrics`` (which
#: the training's validation and the benchmarks import) comes without the command line's Hydra
EXPORTS = {
    "run_eval": "cli",
    **dict.fromkeys(
        ("METHODS", "EvaluationError", "Method", "MethodFactory", "build_methods", "parse_horizons"), "methods"
    ),
    **dict.fromkeys(("is_complete", "method_summary", "read_metrics", "write_results"), "report"),
    **dict.fromkeys(("Evaluation", "EvaluationResult", "PairHook", "PairPredictions", "evaluate"), "run"),
    **dict.fromkeys(("MethodScores", "MetricOptions", "PairScorer"), "scoring"),
}

__all__ = sorted(EXPORTS)


def __getattr__(name: str):
    if name not in EXPORTS:
        raise AttributeError(f"module 'icpflow.evaluation' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"icpflow.evaluation.{EXPORTS[name]}"), name)
