"""Deprecated, removed in 0.3: the last release's ``icpflow.teacher.tracker``, today
``icpflow.teacher.long_horizon``."""

from icpflow.core.deprecation import warn_moved
from icpflow.teacher.long_horizon import (
    HorizonResult,
    SampleFlow,
    long_horizon_flow,
    sample_tracker_flow,
    teacher_on_sample,
)

__all__ = ["HorizonResult", "SampleFlow", "long_horizon_flow", "sample_tracker_flow", "teacher_on_sample"]

warn_moved("icpflow.teacher.tracker", "icpflow.teacher.long_horizon")
