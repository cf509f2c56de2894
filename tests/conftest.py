"""Settings and fixtures shared by every test."""

import os

# OpenMP threads (numba's kernels, torch) that finish their work sleep instead of spinning for their next: the two
# pytest-xdist workers of CI share 2 cores, and a spinning thread takes one from the other worker (the suite: 13.5 ->
# 12.1-12.7 minutes of user CPU, 475 -> 438-472 s; BENCHMARKS.md, "The test suite"). Read once, when OpenMP loads:
# before torch and numba (and inherited by the processes the tests start).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import subprocess  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
import torch  # noqa: E402

import fastflow3d.training.options  # noqa: E402
import icpflow.evaluation.options  # noqa: E402
import icpflow.labelling.options  # noqa: E402

# the structured configs conf/*.yaml extend, as the entry points store them before Hydra composes
icpflow.labelling.options.register()
icpflow.evaluation.options.register()
fastflow3d.training.options.register()


def pytest_addoption(parser):
    parser.addoption(
        "--run-slow", action="store_true", help="also run the tests marked slow (skipped by default; .ci/run runs them)"
    )


#: the files whose tests take longest, longest first (their times in the suite, BENCHMARKS.md, "The test suite"),
#: collected first: pytest-xdist's ``--dist loadfile`` (.ci/run) hands files to its workers in collection order, to
#: whichever is free, so the long files run early and side by side, and the workers end together on short files
#: instead of one running a long file alone at the end
LONGEST_FIRST = (
    "test_gpu_run.py",
    "test_faults.py",
    "test_faults_training.py",
    "test_label.py",
    "test_ddp.py",
    "test_errors_and_signals.py",
    "test_export.py",
    "test_train.py",
    "test_memory_follows_points.py",
    "test_bad_files_sweep.py",
    "test_stream.py",
    "test_model.py",
    "test_console_scripts.py",
    "test_evaluation.py",
    "test_run_folder.py",
    "test_hdbscan_labels.py",
    "test_console.py",
    "test_viz_rerun.py",
    "test_settings.py",
    "test_teacher_long_vehicles.py",
    "test_int8.py",
)


def pytest_collection_modifyitems(config, items):
    """The longest files first (``LONGEST_FIRST``; each file's tests keep their order). Tests marked ``slow`` (whole
    processes of label.py, train.py under DDP, eval.py; trainings of many steps) are skipped unless ``--run-slow``
    is given: ``pytest -q`` stays a few minutes, CI runs everything."""
    first = {name: rank for rank, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: first.get(item.path.name, len(first)))
    if config.getoption("--run-slow"):
        return
    skip = pytest.mark.skip(reason="slow: run with --run-slow (as .ci/run does)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


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


@pytest.fixture(scope="session")
def tiny_student(tmp_path_factory):
    """The tiny student (helpers.training.TINY_MODEL) trained once per session, 5 Adam steps towards the true flow of
    a small synthetic pair (32 beams; every point): ``<session folder>/run/checkpoints/tiny.ckpt``, its stored run
    folders that folder's. Tests copy it (helpers.students.place_checkpoint) rather than change it."""
    from icpflow.datasets.synthetic.reader import SyntheticDataset

    from helpers.students import tiny_checkpoint

    pair = SyntheticDataset(split="test", beams=32, num_sequences=1, frames_per_sequence=2, seed=0)[0]
    return tiny_checkpoint(tmp_path_factory.mktemp("tiny_student") / "run" / "checkpoints" / "tiny.ckpt", pair, 5)


@pytest.fixture(scope="session")
def tiny_pt2_export(tiny_student):
    """``tiny_student``'s export in the .pt2 format only, in export.py's default folder for it (``export`` beside
    it). Tests copy it rather than change it."""
    from fastflow3d.artifact.export import export_checkpoint

    return export_checkpoint(tiny_student, formats=("pt2",))


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
