"""Deprecated, removed in 0.3: the last release's ``icpflow.teacher.registration_cpu``,
today ``icpflow.teacher.registration.cpu``."""

from icpflow.core.deprecation import warn_moved
from icpflow.teacher.registration.cpu import (
    grid_cell,
    register_batch_cpu,
    register_stages_cpu,
)

__all__ = [
    "grid_cell",
    "register_batch_cpu",
    "register_stages_cpu",
]

warn_moved("icpflow.teacher.registration_cpu", "icpflow.teacher.registration.cpu")
