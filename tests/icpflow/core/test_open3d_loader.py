"""icpflow.core.open3d_loader: open3d is imported through it only, and loads on a machine without the system library
libusb-1.0 (a minimal Debian/Ubuntu image, a plain ``pip install`` without root) from the ``libusb-package`` wheel.

The machine without the library is this one with it hidden: a child process in its own mount namespace (``unshare``,
root or an unprivileged user namespace) where every path the loader could find ``libusb-1.0.so.0`` at is covered by
``/dev/null``. A control run in the same namespace proves the hiding (a plain ``import open3d`` fails there)."""

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from icpflow.core.open3d_loader import LIBUSB, LIBUSB_FIX, OPEN3D_FIX

from helpers.data import REPO

#: every folder of Python code in the repository: the packages, the tests, the benchmarks, the scripts
CODE = [
    *REPO.glob("*.py"),
    *(path for folder in ("icpflow", "fastflow3d", "tests", "benchmarks") for path in (REPO / folder).rglob("*.py")),
]


def test_open3d_is_imported_by_the_loader_only():
    importers = set()
    for path in CODE:
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = [alias.name for alias in node.names] if isinstance(node, ast.Import) else []
            names += [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            if any(name == "open3d" or name.startswith("open3d.") for name in names):
                importers.add(str(path.relative_to(REPO)))
    assert importers == {"icpflow/core/open3d_loader.py"}


def system_libusb_paths() -> list[str]:
    """Every existing path under which the loader could find the system's ``libusb-1.0.so.0``: the loader cache's
    entries and the default folders."""
    listed = subprocess.run(["ldconfig", "-p"], capture_output=True, text=True).stdout.splitlines()
    paths = {line.rpartition("=>")[2].strip() for line in listed if LIBUSB in line}
    for folder in ("/lib", "/usr/lib", "/lib64", "/usr/lib64"):
        paths.update(str(path) for path in Path(folder).glob(f"*/{LIBUSB}"))
        paths.add(f"{folder}/{LIBUSB}")
    return sorted(path for path in paths if os.path.exists(path))


def without_system_libusb(*codes: str) -> list[subprocess.CompletedProcess]:
    """Run each Python snippet of ``codes`` in a child process that cannot see the system's libusb (module
    docstring); skips where this machine cannot make a mount namespace."""
    if shutil.which("unshare") is None:
        pytest.skip("no unshare here to hide the system's libusb")
    hide = "".join(f"mount --bind /dev/null '{path}' && " for path in system_libusb_paths())
    env = {key: value for key, value in os.environ.items() if key not in ("LD_LIBRARY_PATH", "LD_PRELOAD")}
    env["PYTHONPATH"] = str(REPO)
    runs = []
    for code in codes:
        command = f"{hide}exec '{sys.executable}' -c \"$0\""
        done = subprocess.run(
            ["unshare", "--mount", "--map-root-user", "sh", "-c", command, code],
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
        )
        if "unshare:" in done.stderr or "mount:" in done.stderr:
            pytest.skip(f"cannot hide the system's libusb here: {done.stderr.strip().splitlines()[-1]}")
        runs.append(done)
    return runs


PLAIN = "import open3d"

#: what a plain install does first with open3d: the ego motion's point-to-plane refinement on a voxel cloud
THROUGH_THE_LOADER = """
import numpy as np
from icpflow.scans.odometry import voxel_cloud
from icpflow.core.open3d_loader import load_open3d, provide_libusb

o3d = load_open3d()
points = np.random.default_rng(0).uniform(-5, 5, (2000, 3))
cloud = voxel_cloud(points, 0.2)
cloud.estimate_normals()
moved = np.eye(4)
moved[0, 3] = 0.05
result = o3d.pipelines.registration.registration_icp(
    cloud, cloud, 0.5, moved, o3d.pipelines.registration.TransformationEstimationPointToPlane()
)
print(provide_libusb())
print(abs(result.transformation[0, 3]) < 1e-3)
"""

#: neither library: no system one (hidden), and libusb-package made unimportable
NEITHER = (
    "import sys; sys.modules['libusb_package'] = None\n"
    "from icpflow.core.open3d_loader import load_open3d\nload_open3d()"
)


def test_open3d_loads_without_the_system_libusb():
    pytest.importorskip("libusb_package", reason="libusb-package not installed")
    plain, loaded, neither = without_system_libusb(PLAIN, THROUGH_THE_LOADER, NEITHER)

    assert plain.returncode != 0 and "libusb-1.0.so.0" in plain.stderr  # the control: the system's copy is hidden

    assert loaded.returncode == 0, loaded.stderr
    source, registered = loaded.stdout.split()
    assert Path(source).parent.name == "libusb_package"  # the wheel's copy, not the system's
    assert registered == "True"

    last = neither.stderr.strip().splitlines()[-1]
    assert last.startswith(f"ImportError: open3d cannot load {LIBUSB} (") and last.endswith(LIBUSB_FIX)


def test_an_install_without_open3d_says_in_one_line_how_to_get_it():
    # a child process: this one has open3d loaded already
    code = (
        "import sys; sys.modules['open3d'] = None\n"
        "from icpflow.core.open3d_loader import load_open3d\n"
        "try:\n    load_open3d()\nexcept ImportError as error:\n    print(error)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out == f"open3d is not installed; {OPEN3D_FIX}\n"
