"""fastflow3d: the FastFlow3D student network, its training on pseudo-flow shards, and export.

Four rooms, imports pointing one way (``tests/test_architecture.py``): ``network`` (the model, voxelisation, the input
contract) <- ``artifact`` (checkpoints and exported files: format, writers, safe loading, engines, export) <-
``inference`` (Predictor, refinement, stream, ``fastflow3d-infer``, the evaluation methods); ``training`` (the
LightningModule, data, loss, schedules, callbacks, trainer, run folder, options) uses ``network`` and ``artifact``.
``inference`` and ``training`` never import each other; ``network`` and ``artifact`` import neither.
"""
