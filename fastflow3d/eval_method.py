"""Deprecated, removed in 0.3: the last release's ``fastflow3d.eval_method``, today
``fastflow3d.inference.eval_methods``."""

from fastflow3d.inference.eval_methods import (
    StreamedStudentMethod,
    StudentMethod,
    refined_streamed_student_method,
    refined_student_method,
    streamed_student_method,
    student_method,
)
from icpflow.core.deprecation import warn_moved

__all__ = [
    "StreamedStudentMethod",
    "StudentMethod",
    "refined_streamed_student_method",
    "refined_student_method",
    "streamed_student_method",
    "student_method",
]

warn_moved("fastflow3d.eval_method", "fastflow3d.inference.eval_methods")
