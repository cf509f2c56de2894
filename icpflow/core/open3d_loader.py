"""open3d, imported through one door: :func:`load_open3d` (every use of open3d in the project calls it; the tests
check that no other module imports open3d).

The open3d wheels link against the system library ``libusb-1.0.so.0``, which minimal Debian/Ubuntu images lack and
only root can install (``apt-get install libusb-1.0-0``). Where the system's loader does not find it, the copy that
the ``libusb-package`` wheel ships (a dependency of this project: a plain ``pip install`` brings it) is loaded into
the process first, with ``RTLD_GLOBAL``: its soname is ``libusb-1.0.so.0``, so open3d's own library resolves to it.
The system's library, where there is one, is kept. Without either, open3d's import fails with one line naming the fix.
"""

from __future__ import annotations

import ctypes
import functools
import sys

from icpflow.core.errors_and_signals import one_line
from icpflow.core.stops import raise_stop_behind

#: the soname of the system library open3d's ``libOpen3D.so`` needs
LIBUSB = "libusb-1.0.so.0"

#: how to get open3d itself, for what needs it (the odometry of pairs without poses, the ``.ply`` / ``.pcd`` readers)
OPEN3D_FIX = "pip install open3d-cpu (Linux x86-64) or pip install open3d (macOS, Windows, Linux Arm)"

#: how to get :data:`LIBUSB`, for the message of an open3d that cannot load it
LIBUSB_FIX = "pip install libusb-package (or, as root: apt-get install libusb-1.0-0)"


@functools.cache
def provide_libusb() -> str | None:
    """Make :data:`LIBUSB` loadable for open3d, once per process. Returns where it came from: ``"system"`` (the
    system's loader finds it), the path of ``libusb-package``'s copy (loaded now, globally), or None (neither: not
    Linux, or neither library is there)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        ctypes.CDLL(LIBUSB, mode=ctypes.RTLD_GLOBAL)
        return "system"
    except OSError:
        pass
    try:
        import libusb_package
    except ImportError as error:
        raise_stop_behind(error)
        return None
    path = libusb_package.get_library_path()
    if path is None:  # a build of the package without the library (another platform)
        return None
    ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
    return str(path)


def load_open3d():
    """The ``open3d`` module, imported after :func:`provide_libusb`. An open3d that still cannot load
    :data:`LIBUSB` raises an ImportError of one line naming the fix (:data:`LIBUSB_FIX`); an install without open3d,
    one naming how to install it (:data:`OPEN3D_FIX`)."""
    provide_libusb()
    try:
        import open3d
    except ModuleNotFoundError as error:  # an install without it (a platform where its marker did not apply)
        raise ImportError(f"open3d is not installed; {OPEN3D_FIX}") from error
    except ImportError as error:
        raise_stop_behind(error)
        if "libusb" not in str(error):
            raise
        raise ImportError(f"open3d cannot load {LIBUSB} ({one_line(error)}); {LIBUSB_FIX}") from error
    return open3d
