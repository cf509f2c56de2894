"""A read-only install with a read-only home runs (``icpflow.core.kernel_cache``): numba's kernels are cached in a
private temporary folder, said in one line; ``NUMBA_CACHE_DIR`` given is never changed."""

import os
import shutil
import subprocess
import sys

from icpflow.core.kernel_cache import choose_kernel_cache

from helpers.data import REPO


def test_a_given_cache_folder_or_a_writable_install_is_left_alone(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "mine"))
    assert choose_kernel_cache(tmp_path) is None and os.environ["NUMBA_CACHE_DIR"] == str(tmp_path / "mine")
    monkeypatch.delenv("NUMBA_CACHE_DIR")
    assert choose_kernel_cache(tmp_path) is None and "NUMBA_CACHE_DIR" not in os.environ  # its __pycache__ is writable


def test_a_read_only_install_and_home_cache_the_kernels_in_a_temporary_folder(tmp_path, mount_tmpfs):
    """The package copied onto a filesystem mounted read-only, HOME read-only too: importing a kernel module and
    running its kernel works, with one line naming the cache folder."""
    install = mount_tmpfs(tmp_path / "install", "64m")
    shutil.copytree(REPO / "icpflow", install / "icpflow", ignore=shutil.ignore_patterns("__pycache__"))
    done = subprocess.run(["mount", "-o", "remount,ro", str(install)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    home = mount_tmpfs(tmp_path / "home", "1m", read_only=True)
    temporary = tmp_path / "tmp"
    temporary.mkdir()
    env = {key: value for key, value in os.environ.items() if key not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}
    env.update(PYTHONPATH=str(install), HOME=str(home), TMPDIR=str(temporary))
    code = (
        "import numpy as np, icpflow; from icpflow.scans.bev import occupied_cells; "
        "points = np.zeros((4, 3), np.float32); occupied_cells(points, np.float32(0.5), np.ones(4, bool)); "
        "print(icpflow.__file__)"
    )
    done = subprocess.run(  # run from elsewhere than the checkout, whose icpflow would come first
        [sys.executable, "-c", code], cwd=temporary, env=env, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-800:]
    assert done.stdout.strip() == str(install / "icpflow" / "__init__.py")
    folder = temporary / f"icpflow-numba-{os.getuid()}"
    said = [line for line in done.stderr.splitlines() if line.startswith("icpflow:")]
    assert said == [
        f"icpflow: {install / 'icpflow'} and {home / '.cache'} are read-only: numba's kernels are cached in {folder} "
        "(NUMBA_CACHE_DIR chooses another)"
    ]
    assert any(folder.rglob("*.nbi"))  # the kernel's cache is there
