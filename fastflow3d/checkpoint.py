"""Deprecated, removed in 0.3: the last release's ``fastflow3d.checkpoint``, today
``fastflow3d.artifact.checkpoint``."""

from fastflow3d.artifact.checkpoint import MODEL_TARGET, CheckpointError, build_student, load_student, read_checkpoint
from icpflow.core.deprecation import warn_moved

__all__ = ["MODEL_TARGET", "CheckpointError", "build_student", "load_student", "read_checkpoint"]

warn_moved("fastflow3d.checkpoint", "fastflow3d.artifact.checkpoint")
