"""Deprecated, removed in 0.3: the last release's ``fastflow3d.module``, today ``fastflow3d.training.student_module``.
Old checkpoints name its class: ``fastflow3d.artifact.checkpoint.read_checkpoint`` reads it as today's path."""

from fastflow3d.training.student_module import LOSSES, NonFiniteLoss, StudentModule, log
from icpflow.core.deprecation import warn_moved

__all__ = ["LOSSES", "NonFiniteLoss", "StudentModule", "log"]

warn_moved("fastflow3d.module", "fastflow3d.training.student_module")
