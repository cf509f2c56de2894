"""Deprecated, removed in 0.3: the last release's ``fastflow3d.callbacks``, today ``fastflow3d.training.callbacks``.
Old checkpoints name its classes: ``fastflow3d.artifact.checkpoint.read_checkpoint`` reads them as today's paths."""

from fastflow3d.training.callbacks import (
    BEST_STATE_KEYS,
    AtomicCheckpointIO,
    LastCheckpoint,
    ModelSize,
    TrainingStopped,
    ValidateAtEnd,
    keep_best_after_resume,
    log,
    progress_bar,
    set_best_checkpoints,
)
from icpflow.core.deprecation import warn_moved

__all__ = [
    "BEST_STATE_KEYS",
    "AtomicCheckpointIO",
    "LastCheckpoint",
    "ModelSize",
    "TrainingStopped",
    "ValidateAtEnd",
    "keep_best_after_resume",
    "log",
    "progress_bar",
    "set_best_checkpoints",
]

warn_moved("fastflow3d.callbacks", "fastflow3d.training.callbacks")
