"""Deprecated, removed in 0.3: the last release's ``icpflow.console``, today ``icpflow.core.console``."""

from icpflow.core.console import (
    LIGHTNING_LOGGERS,
    NOISE,
    NOISE_WARNINGS,
    ConsoleFormatter,
    NoiseFilter,
    Progress,
    ProgressSafeHandler,
    WorkerHandler,
    captured_output,
    quiet,
    recorded_warnings,
    worker_logging,
)
from icpflow.core.deprecation import warn_moved

__all__ = [
    "ConsoleFormatter",
    "LIGHTNING_LOGGERS",
    "NOISE",
    "NOISE_WARNINGS",
    "NoiseFilter",
    "Progress",
    "ProgressSafeHandler",
    "WorkerHandler",
    "captured_output",
    "quiet",
    "recorded_warnings",
    "worker_logging",
]

warn_moved("icpflow.console", "icpflow.core.console")
