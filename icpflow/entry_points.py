"""Deprecated, removed in 0.3: the last release's ``icpflow.entry_points``, today ``icpflow.core.entry_points``."""

from icpflow.core.deprecation import warn_moved
from icpflow.core.entry_points import (
    CHECKOUT_CONF,
    CONFIG_PACKAGE,
    config_path,
    hydra_entry,
    version_line,
)

__all__ = [
    "CHECKOUT_CONF",
    "CONFIG_PACKAGE",
    "config_path",
    "hydra_entry",
    "version_line",
]

warn_moved("icpflow.entry_points", "icpflow.core.entry_points")
