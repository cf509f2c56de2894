"""Deprecated, removed in 0.3: the last release's ``fastflow3d.predictor``, today ``fastflow3d.inference.predictor``
(its other names in ``fastflow3d.inference.prediction`` and ``fastflow3d.inference.model_loading``)."""

from fastflow3d.inference.model_loading import checkpoint_contract, given_contract
from fastflow3d.inference.prediction import Prediction, PredictorError, PredictorWarning, as_points
from fastflow3d.inference.predictor import Predictor
from icpflow.core.deprecation import warn_moved

__all__ = [
    "Prediction",
    "Predictor",
    "PredictorError",
    "PredictorWarning",
    "as_points",
    "checkpoint_contract",
    "given_contract",
]

warn_moved("fastflow3d.predictor", "fastflow3d.inference.predictor", "from fastflow3d import Predictor")
