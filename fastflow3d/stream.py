"""Deprecated, removed in 0.3: the last release's ``fastflow3d.stream``, today ``fastflow3d.inference.stream``."""

from fastflow3d.inference.stream import FlowStream, StreamStep, StreamWarning
from icpflow.core.deprecation import warn_moved

__all__ = ["FlowStream", "StreamStep", "StreamWarning"]

warn_moved("fastflow3d.stream", "fastflow3d.inference.stream", "from fastflow3d import FlowStream")
