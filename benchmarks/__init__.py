"""Speed and quality scripts of the teacher and the student (``benchmarks/README.md`` lists them), run from the
checkout's root as ``python -m benchmarks.<name> --help``; shared helpers in ``benchmarks.common`` and
``benchmarks.training_runs``; one-off studies, frozen, in ``benchmarks.studies``. Figures: BENCHMARKS.md."""
