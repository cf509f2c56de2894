"""Deprecated, removed in 0.3: the last release's ``icpflow.threads``, today ``icpflow.core.threads``."""

from icpflow.core.deprecation import warn_moved
from icpflow.core.threads import (
    available_cores,
    cpu_fields,
    thread_limit,
)

__all__ = [
    "available_cores",
    "cpu_fields",
    "thread_limit",
]

warn_moved("icpflow.threads", "icpflow.core.threads")
