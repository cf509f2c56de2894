"""Deprecated, removed in 0.3: the last release's ``icpflow.datasets.io``, today ``icpflow.datasets.file_formats``."""

from icpflow.core.deprecation import warn_moved
from icpflow.datasets.file_formats import (
    BIN_COLUMNS,
    BIN_MAX_RANGE,
    BIN_PLAUSIBLE_MEDIAN,
    PLY_SIZES,
    SCAN_SUFFIXES,
    check_claim,
    check_pcd_complete,
    check_ply_complete,
    fail,
    list_scans,
    load_npy,
    load_npz,
    natural_key,
    read_bin,
    read_feather,
    read_pose_lines,
    read_poses,
    read_scan,
)

__all__ = [
    "BIN_COLUMNS",
    "BIN_MAX_RANGE",
    "BIN_PLAUSIBLE_MEDIAN",
    "PLY_SIZES",
    "SCAN_SUFFIXES",
    "check_claim",
    "check_pcd_complete",
    "check_ply_complete",
    "fail",
    "list_scans",
    "load_npy",
    "load_npz",
    "natural_key",
    "read_bin",
    "read_feather",
    "read_pose_lines",
    "read_poses",
    "read_scan",
]

warn_moved("icpflow.datasets.io", "icpflow.datasets.file_formats")
