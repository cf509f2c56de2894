"""fastflow3d: the FastFlow3D student network, its training on pseudo-flow shards, and export.

Four rooms, imports pointing one way (``tests/project/test_architecture.py``): ``network`` (the model, voxelisation, the
input contract) <- ``artifact`` (checkpoints and exported files: format, writers, safe loading, engines, export) <-
``inference`` (Predictor, refinement, stream, ``fastflow3d-infer``, the evaluation methods); ``training`` (the
LightningModule, data, loss, schedules, callbacks, trainer, run folder, options) uses ``network`` and ``artifact``.
``inference`` and ``training`` never import each other; ``network`` and ``artifact`` import neither.

The stable API: ``from fastflow3d import Predictor, FlowStream, Prediction``. The modules beside the rooms
(``fastflow3d/predictor.py``, ``stream.py``, ``infer.py``, ...) are the last release's paths, kept until 0.3: each
re-exports today's objects with a DeprecationWarning naming their room (``icpflow.core.deprecation``); nothing imports
them.
"""

__all__ = ["FlowStream", "Prediction", "Predictor"]


def __getattr__(name: str):
    """Lazy exports: ``from fastflow3d import Predictor, FlowStream, Prediction`` without importing torch and the
    engines on ``import fastflow3d`` (the old module paths, ``fastflow3d.predictor`` ..., import the same objects
    with a DeprecationWarning until 0.3: ``icpflow.core.deprecation``)."""
    if name == "Predictor":
        from fastflow3d.inference.predictor import Predictor

        return Predictor
    if name == "FlowStream":
        from fastflow3d.inference.stream import FlowStream

        return FlowStream
    if name == "Prediction":
        from fastflow3d.inference.prediction import Prediction

        return Prediction
    raise AttributeError(f"module 'fastflow3d' has no attribute {name!r}")
