"""Where numba caches the kernels' machine code when the install cannot hold it.

numba caches each ``@numba.njit(cache=True)`` kernel beside its source (``__pycache__``) or, where that folder is
read-only (an installed wheel), in the user's cache folder (``~/.cache/numba``). With both read-only (a read-only
install and home: a container, a shared cluster account) it finds no place and refuses to define the kernel at import
("no locator available"). :func:`choose_kernel_cache` then names a private folder in the system's temporary folder
as ``NUMBA_CACHE_DIR`` before any kernel is defined, and says so in one line; ``NUMBA_CACHE_DIR`` set by the user is
never changed. Only the standard library is imported here (``icpflow`` calls it on import).
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

#: the package whose kernels are cached (its folder: numba's first choice)
PACKAGE = Path(__file__).resolve().parents[1]


def _writable(folder: Path) -> bool:
    """True where ``folder`` exists or can be made, and can be written."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(folder, os.W_OK)


def choose_kernel_cache(package: Path = PACKAGE, stream=None) -> str | None:
    """The folder set as ``NUMBA_CACHE_DIR`` (said on ``stream``, stderr), or None where numba has a place of its
    own: ``NUMBA_CACHE_DIR`` given, the package's ``__pycache__`` writable, or the user's cache folder."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    if os.access(package, os.W_OK) and _writable(package / "__pycache__"):
        return None
    user = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "numba"
    if _writable(user):
        return None
    folder = Path(tempfile.gettempdir()) / f"icpflow-numba-{os.getuid() if hasattr(os, 'getuid') else 'user'}"
    stream = stream or sys.stderr
    if not _writable(folder):
        print(f"icpflow: no writable folder for numba's kernel cache ({package}, {user}, {folder} are read-only): "
              "set NUMBA_CACHE_DIR to a writable folder", file=stream)  # fmt: skip
        return None
    os.environ["NUMBA_CACHE_DIR"] = str(folder)
    numba = sys.modules.get("numba")
    if numba is not None:  # imported before icpflow: its configuration is read already
        numba.config.CACHE_DIR = str(folder)
    print(f"icpflow: {package} and {user.parent} are read-only: numba's kernels are cached in {folder} "
          "(NUMBA_CACHE_DIR chooses another)", file=stream)  # fmt: skip
    return str(folder)
