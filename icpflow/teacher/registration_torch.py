"""Deprecated, removed in 0.3: the last release's ``icpflow.teacher.registration_torch``,
today ``icpflow.teacher.registration.torch_batch``."""

from icpflow.core.deprecation import warn_moved
from icpflow.teacher.registration.torch_batch import (
    register_batch_torch,
)

__all__ = [
    "register_batch_torch",
]

warn_moved("icpflow.teacher.registration_torch", "icpflow.teacher.registration.torch_batch")
