"""``label.py`` started from a folder it cannot write (an installed checkout, a shared drive): Hydra's record of the
launch goes under ``out_dir`` (``<out_dir>/.hydra``: ``icpflow.core.settings.run_folder``) and the run labels."""

import os
import subprocess
import sys

from icpflow.core.settings import run_folder

from helpers.data import REPO


def test_the_run_folder_follows_a_writable_working_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert run_folder("outputs/hydra/label", "/x/labels") == "outputs/hydra/label"


def test_label_from_a_read_only_folder_writes_only_under_out_dir(tmp_path, mount_tmpfs):
    cwd = mount_tmpfs(tmp_path / "read_only", "1m", read_only=True)
    assert not os.access(cwd, os.W_OK)
    assert run_folder("outputs/hydra/label", str(tmp_path / "labels")) == "outputs/hydra/label"  # cwd is tmp_path
    out = tmp_path / "labels"
    done = subprocess.run(
        [sys.executable, str(REPO / "label.py"), "dataset.reader.num_sequences=1",
         "dataset.reader.frames_per_sequence=2", "dataset.reader.beams=32", f"out_dir={out}"],
        cwd=cwd, capture_output=True, text=True, timeout=600, env={**os.environ, "PYTHONPATH": str(REPO)},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-800:]
    assert (out / "index.json").is_file() and any((out / ".hydra").iterdir())
