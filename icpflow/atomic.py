"""Deprecated, removed in 0.3: the last release's ``icpflow.atomic``, today ``icpflow.core.atomic``."""

from icpflow.core.atomic import (
    FolderInUse,
    WriteError,
    atomic_directory,
    atomic_path,
    folder_lock,
    fsync_path,
    temporary_name,
    write_text_atomic,
)
from icpflow.core.deprecation import warn_moved

__all__ = [
    "FolderInUse",
    "WriteError",
    "atomic_directory",
    "atomic_path",
    "folder_lock",
    "fsync_path",
    "temporary_name",
    "write_text_atomic",
]

warn_moved("icpflow.atomic", "icpflow.core.atomic")
