"""Deprecated, removed in 0.3: the last release's ``fastflow3d.export``, today ``fastflow3d.artifact.export``."""

from fastflow3d.artifact.export import (
    CHECK_SIZES,
    EXPECTED,
    PARITY_TOLERANCE,
    ExportError,
    check_inputs,
    check_replaceable,
    default_export_dir,
    export_checkpoint,
    export_model,
    measure_parity,
    parse_formats,
    quiet_exporters,
    run_export,
)
from icpflow.core.deprecation import warn_moved

__all__ = [
    "CHECK_SIZES",
    "EXPECTED",
    "PARITY_TOLERANCE",
    "ExportError",
    "check_inputs",
    "check_replaceable",
    "default_export_dir",
    "export_checkpoint",
    "export_model",
    "measure_parity",
    "parse_formats",
    "quiet_exporters",
    "run_export",
]

warn_moved("fastflow3d.export", "fastflow3d.artifact.export")
