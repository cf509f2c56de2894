"""Deprecated, removed in 0.3: the last release's ``icpflow.options``, today ``icpflow.labelling.options``
(``label.py``'s and ``DatasetOptions``) and ``icpflow.evaluation.options`` (``eval.py``'s).
Importing it stores both schemas, as its ``register()`` did; ``register`` stays callable (idempotent)."""

from icpflow.core.deprecation import warn_moved
from icpflow.evaluation.options import EvalOptions
from icpflow.evaluation.options import register as register_eval
from icpflow.labelling.options import DatasetOptions, LabellerOptions, LabelOptions, RayOptions, TeacherOverrides
from icpflow.labelling.options import register as register

__all__ = [
    "DatasetOptions",
    "EvalOptions",
    "LabelOptions",
    "LabellerOptions",
    "RayOptions",
    "TeacherOverrides",
    "register",
]

register_eval()  # the old register() stored both schemas

warn_moved("icpflow.options", "icpflow.labelling.options", "icpflow.evaluation.options for EvalOptions")
