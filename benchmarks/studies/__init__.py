"""One-off studies, frozen: each answered a question of its issue and is kept as it ran, with a first line naming
the commit it measured and the BENCHMARKS.md section holding its figures. Run from the checkout's root as
``python -m benchmarks.studies.<name>``; they are not maintained with the lasting scripts beside ``benchmarks/``."""
