"""``fastflow3d-eval`` and ``eval.py``: the teacher wing's evaluation (``icpflow.evaluation.cli.main``,
``conf/eval.yaml``) with the student's methods added (``fastflow3d.inference.eval_methods``); the teacher wing cannot
name them itself (it never imports this one)."""

from __future__ import annotations

from fastflow3d.inference.eval_methods import (
    refined_streamed_student_method,
    refined_student_method,
    streamed_student_method,
    student_method,
)
from icpflow.evaluation import cli

#: the student's methods by name, as ``method=[...]`` names them
STUDENT_METHODS = {
    "student": student_method,
    "student+refine": refined_student_method,
    "student-stream": streamed_student_method,  # nothing given: the stream's ego motion and ground
    "student-stream+refine": refined_streamed_student_method,  # the same, refined (fastflow3d-infer --refine)
}


def main() -> None:
    """``fastflow3d-eval`` and ``eval.py``: evaluate as ``conf/eval.yaml`` and the command line say, the student's
    methods among the teacher wing's."""
    cli.main(extra_methods=STUDENT_METHODS)
