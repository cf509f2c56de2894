"""Deprecated, removed in 0.3: the last release's ``icpflow.errors_and_signals``,
today ``icpflow.core.errors_and_signals``."""

from icpflow.core.deprecation import warn_moved
from icpflow.core.errors_and_signals import (
    FIXES,
    FULL_ERROR,
    MARKER,
    STOP_SIGNALS,
    Stop,
    error_line,
    exit_status,
    launching_process,
    on_signals,
    one_line,
    os_error_line,
    raise_stop,
    reported,
    run,
    signal_words,
    signals_held,
    stop_on_signals,
    stop_signum,
)

__all__ = [
    "FIXES",
    "FULL_ERROR",
    "MARKER",
    "STOP_SIGNALS",
    "Stop",
    "error_line",
    "exit_status",
    "launching_process",
    "on_signals",
    "one_line",
    "os_error_line",
    "raise_stop",
    "reported",
    "run",
    "signal_words",
    "signals_held",
    "stop_on_signals",
    "stop_signum",
]

warn_moved("icpflow.errors_and_signals", "icpflow.core.errors_and_signals")
