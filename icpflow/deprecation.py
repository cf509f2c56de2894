"""Deprecated, removed in 0.3: the last release's ``icpflow.deprecation``, today ``icpflow.core.deprecation``."""

from icpflow.core.deprecation import (
    REMOVAL,
    moved_attribute,
    moved_message,
    warn_moved,
)

__all__ = [
    "REMOVAL",
    "moved_attribute",
    "moved_message",
    "warn_moved",
]

warn_moved("icpflow.deprecation", "icpflow.core.deprecation")
