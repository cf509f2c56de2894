"""Deprecated, removed in 0.3: the last release's ``icpflow.open3d_loader``, today ``icpflow.core.open3d_loader``."""

from icpflow.core.deprecation import warn_moved
from icpflow.core.open3d_loader import (
    LIBUSB,
    LIBUSB_FIX,
    OPEN3D_FIX,
    load_open3d,
    provide_libusb,
)

__all__ = [
    "LIBUSB",
    "LIBUSB_FIX",
    "OPEN3D_FIX",
    "load_open3d",
    "provide_libusb",
]

warn_moved("icpflow.open3d_loader", "icpflow.core.open3d_loader")
