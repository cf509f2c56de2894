"""Deprecated, removed in 0.3: the last release's ``fastflow3d.runtime``, today ``fastflow3d.artifact.engines``
(``default_threads``: ``icpflow.core.threads.available_cores``; ``runtime_network``: gone, ``engines.load_network``
opens
every model file)."""

from fastflow3d.artifact.engines import (
    BF16_TOLERANCE,
    PRECISIONS,
    RUNTIMES,
    OpenVinoNetwork,
    cpu_only,
    ort_session_options,
)
from icpflow.core.deprecation import warn_moved
from icpflow.core.threads import available_cores as default_threads

__all__ = [
    "BF16_TOLERANCE",
    "PRECISIONS",
    "RUNTIMES",
    "OpenVinoNetwork",
    "cpu_only",
    "default_threads",
    "ort_session_options",
]

warn_moved("fastflow3d.runtime", "fastflow3d.artifact.engines")
