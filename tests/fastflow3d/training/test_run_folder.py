"""One run per folder (issue 31, point 3): ``out_dir``'s lock, no silent overwrite of another run's checkpoints
(``overwrite=true`` removes the names a run writes, and refuses where a user's checkpoint is there),
and a resume that names every setting it does not take."""

from __future__ import annotations

import logging
import os
import subprocess

import pytest
from hydra.errors import ConfigCompositionException

from fastflow3d.training.run_folder import TrainError
from fastflow3d.training.trainer import fit
from icpflow.core.atomic import FolderInUse, folder_lock
from icpflow.core.errors_and_signals import error_line
from icpflow.datasets.synthetic.reader import SyntheticDataset

from helpers.shards import write_pseudo_labels
from helpers.training import train_cfg


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    dataset = SyntheticDataset(split="test", beams=32, num_sequences=1, frames_per_sequence=3, seed=0)
    return write_pseudo_labels(tmp_path_factory.mktemp("shards"), [dataset[0], dataset[1]])


def _cfg(tmp_path, shards, *overrides):
    return train_cfg(tmp_path, shards, shards, "trainer.max_steps=2", "trainer.val_check_interval=2", *overrides)


def _dead_pid() -> int:
    process = subprocess.Popen(["true"])
    process.wait()
    return process.pid


def test_the_lock_refuses_a_live_holder_and_takes_over_a_dead_ones(tmp_path):
    host = os.uname().nodename
    (tmp_path / ".lock").write_text(f"{os.getppid()} {host}\n")
    with pytest.raises(FolderInUse, match=rf"in use by train.py pid {os.getppid()} \(lock .*\.lock\); wait"):
        with folder_lock(tmp_path, "train.py"):
            pass
    (tmp_path / ".lock").write_text(f"{_dead_pid()} {host}\n")
    with folder_lock(tmp_path, "train.py") as lock:
        assert lock.read_text() == f"{os.getpid()} {host}\n"
    assert not (tmp_path / ".lock").exists()
    (tmp_path / ".lock").write_text("123 another-host\n")
    with pytest.raises(FolderInUse, match="in use by train.py on host another-host"):
        with folder_lock(tmp_path, "train.py"):
            pass


def test_a_second_run_into_a_held_folder_is_refused_in_one_line(shards, tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / ".lock").write_text(f"{os.getppid()} {os.uname().nodename}\n")
    with pytest.raises(TrainError, match=rf"run: in use by train.py pid {os.getppid()}") as caught:
        fit(_cfg(tmp_path, shards))
    assert "\n" not in str(caught.value) and not (run / "checkpoints").exists()


def test_another_runs_checkpoints_are_never_overwritten_silently(shards, tmp_path, caplog):
    fit(_cfg(tmp_path, shards))
    checkpoints = tmp_path / "run" / "checkpoints"
    before = {path.name: path.stat().st_mtime_ns for path in checkpoints.glob("*.ckpt")}
    assert "last.ckpt" in before and not (tmp_path / "run" / ".lock").exists()
    with pytest.raises(
        TrainError, match="holds another run's checkpoints \\(last.ckpt\\); resume it with ckpt_path=last"
    ):
        fit(_cfg(tmp_path, shards))
    assert {path.name: path.stat().st_mtime_ns for path in checkpoints.glob("*.ckpt")} == before
    mine = checkpoints / "my_copy.ckpt"  # a user's checkpoint kept there: not the previous run's to remove
    mine.write_bytes((checkpoints / "last.ckpt").read_bytes())
    (checkpoints / "notes.txt").write_text("mine")
    with pytest.raises(TrainError, match=r"my_copy.ckpt is not a checkpoint a run names \(last.ckpt, best-step\*\)"):
        fit(_cfg(tmp_path, shards, "overwrite=true"))
    assert {path.name: path.stat().st_mtime_ns for path in checkpoints.glob("*.ckpt") if path != mine} == before
    mine.unlink()
    with caplog.at_level(logging.WARNING, logger="fastflow3d.training"):
        fit(_cfg(tmp_path, shards, "overwrite=true"))
    assert "overwrite=true: removed" in caplog.text
    assert (checkpoints / "notes.txt").read_text() == "mine"
    assert (checkpoints / "last.ckpt").stat().st_mtime_ns != before["last.ckpt"]


def test_a_resume_names_every_setting_it_does_not_take(shards, tmp_path, caplog):
    fit(_cfg(tmp_path, shards))
    for override, words in (
        ("model.cell=0.5", r"model.cell=1.0 \(this run: 0.5\)"),
        ("data.batch_size=3", r"data.batch_size=\d+ \(this run: 3\)"),
    ):
        with pytest.raises(TrainError, match=rf"ckpt_path=last: .* was trained with other settings: {words}") as caught:
            fit(_cfg(tmp_path, shards, "ckpt_path=last", "trainer.max_steps=4", override))
        assert "\n" not in str(caught.value)
    with caplog.at_level(logging.WARNING, logger="fastflow3d.training"):
        fit(_cfg(tmp_path, shards, "ckpt_path=last", "trainer.max_steps=4", "optim.lr=0.5"))
    assert "not applied: optim.lr=" in caplog.text and "(this run: 0.5)" in caplog.text


def test_a_data_folder_that_is_not_a_path_is_one_line(shards, tmp_path):
    """A list is refused while composing (data.train is a text in the schema); an empty path before any work."""
    with pytest.raises(ConfigCompositionException) as refused:
        _cfg(tmp_path, shards, "data.train=[a,b]")
    assert error_line(refused.value).startswith("data.train=[a,b]: expected a text, got '[a,b]'")
    with pytest.raises(TrainError, match="^data.train is empty; give a label folder"):
        fit(_cfg(tmp_path, shards, "data.train="))


def test_validation_on_the_training_folder_is_said(shards, tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="fastflow3d.training"):
        fit(_cfg(tmp_path, shards, "trainer.fast_dev_run=true"))
    assert "data.val is data.train" in caplog.text


def test_a_labeller_config_with_a_python_tag_is_one_line_naming_the_shard(shards, tmp_path):
    import shutil

    import h5py

    from fastflow3d.network.voxelize import Grid
    from fastflow3d.training.data import DataError, labeller_contract

    copy = tmp_path / "labels"
    shutil.copytree(shards, copy)
    shard = sorted(copy.glob("shard_*.h5"))[0]
    with h5py.File(shard, "r+") as handle:
        handle.attrs["config"] = "teacher: !!python/object/apply:os.system ['touch pwned']\n"
    with pytest.raises(DataError, match=rf"{shard}: its labeller config is not plain YAML \(ConstructorError"):
        labeller_contract(copy, True, Grid())
    assert not (tmp_path / "pwned").exists() and not os.path.exists("pwned")


def test_validation_samples_that_are_training_samples_are_said(shards, tmp_path, caplog):
    import shutil

    copy = tmp_path / "val"
    shutil.copytree(shards, copy)
    with caplog.at_level(logging.WARNING, logger="fastflow3d.training"):
        fit(train_cfg(tmp_path, shards, copy, "trainer.fast_dev_run=true"))
    assert "data.val shares 2 of its 2 sample ids with data.train" in caplog.text


def test_what_the_data_or_the_folder_cannot_give_is_refused_before_any_work(shards, tmp_path, caplog):
    """Issue 45.5: out_dir a label folder; '~' that no shell expanded; more processes than samples (an "unexpected
    AssertionError" and gloo noise); an effective batch larger than the data (it said 64 and stepped on 2); a
    resume on other data (it was silent)."""
    with pytest.raises(TrainError, match=r"out_dir=.* holds label.py's shards \(index.json\)"):
        fit(train_cfg(tmp_path, shards, shards, f"out_dir={shards}"))
    with pytest.raises(TrainError, match=r"data.train holds 2 sample\(s\), fewer than the 3 processes"):
        fit(_cfg(tmp_path, shards, "trainer=ddp_cpu", "trainer.devices=3"))
    with pytest.raises(TrainError, match=r"effective_batch=64 is more than the 2 training samples"):
        fit(_cfg(tmp_path, shards, "effective_batch=64", "data.batch_size=2"))
    assert not (tmp_path / "run" / "checkpoints").exists()
    fit(_cfg(tmp_path, shards))
    other = tmp_path / "moved"
    other.symlink_to(shards)
    with caplog.at_level(logging.WARNING, logger="fastflow3d.training"):
        fit(_cfg(tmp_path, shards, "ckpt_path=auto", "trainer.max_steps=4", f"data.train={other}"))
    assert "with other data than it was trained on: data.train=" in caplog.text
