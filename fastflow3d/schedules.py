"""Deprecated, removed in 0.3: the last release's ``fastflow3d.schedules``, today ``fastflow3d.training.schedules``.
Old checkpoints name its functions: ``fastflow3d.artifact.checkpoint.read_checkpoint`` reads them as today's paths."""

from fastflow3d.training.schedules import warmup_cosine, warmup_multistep
from icpflow.core.deprecation import warn_moved

__all__ = ["warmup_cosine", "warmup_multistep"]

warn_moved("fastflow3d.schedules", "fastflow3d.training.schedules")
