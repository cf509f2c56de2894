"""Deprecated, removed in 0.3: ``python -m fastflow3d.infer`` and the last release's module ``fastflow3d.infer``,
today ``fastflow3d.inference.cli`` (the ``fastflow3d-infer`` command; its scan files in
``fastflow3d.inference.scan_files``, a stream's output folder in ``fastflow3d.inference.stream_folder``)."""

import sys

from fastflow3d.inference.cli import (
    given_preprocessing,
    infer,
    infer_stream,
    load_predictor,
    main,
    parse_args,
    sensor_height,
)
from fastflow3d.inference.scan_files import NPZ_KEYS, read_raw_scan, read_transforms, refuse_input_as_output, write_flow
from fastflow3d.inference.stream_folder import claim_output_folder, read_manifest, stream_files, stream_manifest
from icpflow.core.deprecation import moved_message, warn_moved

__all__ = [
    "NPZ_KEYS",
    "claim_output_folder",
    "given_preprocessing",
    "infer",
    "infer_stream",
    "load_predictor",
    "main",
    "parse_args",
    "read_manifest",
    "read_raw_scan",
    "read_transforms",
    "refuse_input_as_output",
    "sensor_height",
    "stream_files",
    "stream_manifest",
    "write_flow",
]

warn_moved("fastflow3d.infer", "fastflow3d.inference.cli", "the fastflow3d-infer command")

if __name__ == "__main__":
    # run as a command, the warning above is hidden (Python shows a DeprecationWarning only where __main__'s own code
    # raises it), so the command says it on stderr itself, then runs as before
    notice = moved_message("python -m fastflow3d.infer", "fastflow3d-infer", "python -m fastflow3d.inference.cli")
    print(f"infer: warning: {notice}", file=sys.stderr)
    sys.exit(main())
