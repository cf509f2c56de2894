"""Settings and fixtures shared by every test."""

import subprocess
from pathlib import Path

import pytest
import torch

import fastflow3d.training.options
import icpflow.options

# the structured configs conf/*.yaml extend, as the entry points store them before Hydra composes
icpflow.options.register()
fastflow3d.training.options.register()


@pytest.fixture(scope="session", autouse=True)
def one_torch_thread():
    """One torch thread: the test networks are tiny, and on a busy 2-core machine (CI) two threads fighting over
    the cores make them several times slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def reference(tmp_path_factory):
    """The small world labelled once per session by an uninterrupted single-worker run (helpers.labelling): 5 samples
    in shards of 2, 2, 1; the output every faulted, resumed or parallel run must reproduce."""
    from icpflow.labelling.cli import label

    from helpers.labelling import label_cfg

    out = tmp_path_factory.mktemp("reference") / "labels"
    assert label(label_cfg(out), progress=False) == 0
    return out


@pytest.fixture
def mount_tmpfs(tmp_path):
    """``mount_tmpfs(folder, size, read_only=False)``: a real small filesystem at ``folder`` (unmounted after the
    test); skips where this user may not mount one."""
    mounted = []

    def mount(folder: Path, size: str, read_only: bool = False) -> Path:
        folder.mkdir(parents=True, exist_ok=True)
        options = f"size={size}" + (",ro" if read_only else "")
        result = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)], capture_output=True)
        if result.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here (needs root): {result.stderr.decode().strip()}")
        mounted.append(folder)
        return folder

    yield mount
    for folder in reversed(mounted):
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)
