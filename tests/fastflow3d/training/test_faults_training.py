"""Faults of training, export, evaluation and inference, each reproduced (issue 20): the run says what happened in
one line naming the option or the file (exit 2; 143 / 130 for SIGTERM / SIGINT), keeps what was written before,
leaves no process and no half-written file behind. Real signals; a real full or read-only filesystem (a small
tmpfs, where this user may mount one) and an injected ENOSPC otherwise."""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from fastflow3d.artifact.export import export_checkpoint
from fastflow3d.artifact.file_format import FILE_NAMES, METADATA_NAME, sha256_file
from fastflow3d.inference.cli import main as infer_main
from fastflow3d.training.run_folder import TrainError
from fastflow3d.training.trainer import fit
from icpflow.core.atomic import WriteError
from icpflow.datasets.synthetic.reader import SyntheticDataset

from helpers.data import REPO
from helpers.disk import fail_fsync_after
from helpers.labelling import TESTS_ENV, default_sigint, none_left_within
from helpers.shards import write_pseudo_labels
from helpers.training import TINY, compose_train, train_cfg

READER = {"split": "train", "num_sequences": 1, "frames_per_sequence": 3, "beams": 32, "azimuth_resolution_deg": 2.0}
STEPS = ["trainer.val_check_interval=2", "data.batch_size=1", "metrics.bev_every=0"]


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    """Two pairs of the small world as label.py shards (pseudo-labels = ground truth)."""
    dataset = SyntheticDataset(**READER)
    return write_pseudo_labels(
        tmp_path_factory.mktemp("shards") / "train", [dataset.pair(i) for i in range(len(dataset))]
    )


def _train(out_dir, shard_dir, *overrides) -> list[str]:
    """The command line of train.py on the tiny network (helpers.training.TINY)."""
    data = [f"data.train={shard_dir}", f"data.val={shard_dir}", f"out_dir={out_dir}"]
    return [sys.executable, str(REPO / "train.py"), *data, *TINY, *overrides]


def _popen(args, cwd) -> subprocess.Popen:
    """A script in its own session (process group = its pid), Ctrl-C at its default."""
    return subprocess.Popen(
        args,
        cwd=cwd,
        env={key: value for key, value in TESTS_ENV.items() if key != "HYDRA_FULL_ERROR"},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=default_sigint,
    )


def _no_temporary_files(folder: Path) -> bool:
    return not [path for path in folder.rglob("*") if ".tmp-" in path.name]


def _lines(err: str, prog: str) -> list[str]:
    """The script's own lines on stderr (Lightning's and Hydra's info lines, and the line announcing a long step,
    ``<prog>: exporting ...``, left out)."""
    return [
        line for line in err.splitlines() if line.startswith(f"{prog}:") and not line.startswith(f"{prog}: exporting")
    ]


def _state(checkpoint: Path) -> dict:
    """The ModelCheckpoint state saved in a checkpoint."""
    callbacks = torch.load(checkpoint, weights_only=True, mmap=True)["callbacks"]
    return next(value for key, value in callbacks.items() if key.startswith("ModelCheckpoint"))


# ------------------------------------------------------------------------------------- 1. resume: one true best


def test_last_checkpoint_knows_the_best_and_a_resume_keeps_only_the_truly_best(shards, tmp_path):
    """Issue 20.1: last.ckpt holds the ModelCheckpoint state of its own validation (it lagged one behind, so a
    resume saved worse checkpoints as best beside the true one). On a resume, a best checkpoint the state does not
    know (a run killed between the two saves, an older version) is weighed by its stored score; exactly one is
    kept, the truly best, and the export takes it."""
    checkpoints = tmp_path / "run" / "checkpoints"
    fit(train_cfg(tmp_path, shards, shards, "trainer.max_steps=4", *STEPS))
    (best,) = checkpoints.glob("best-*.ckpt")
    assert best.name.startswith("best-step0000004-") or best.name.startswith("best-step0000002-")
    assert _state(checkpoints / "last.ckpt")["best_model_path"] == str(best)  # the state after step 4's validation

    def plant(name: str, score: float) -> Path:
        checkpoint = torch.load(best, weights_only=True)
        key = next(key for key in checkpoint["callbacks"] if key.startswith("ModelCheckpoint"))
        checkpoint["callbacks"][key]["current_score"] = torch.tensor(score)
        torch.save(checkpoint, checkpoints / name)
        return checkpoints / name

    truly_best = plant("best-step0000003-dynEPE0.0001.ckpt", 1e-4)  # better than anything this run reaches
    worse = plant("best-step0000001-dynEPE9.9000.ckpt", 9.9)
    trainer = fit(
        train_cfg(tmp_path, shards, shards, "trainer.max_steps=6", "ckpt_path=last", "export.formats=[pt2]", *STEPS)
    )
    assert trainer.global_step == 6
    assert sorted(checkpoints.glob("best-*.ckpt")) == [truly_best] and not worse.exists()
    assert _state(checkpoints / "last.ckpt")["best_model_path"] == str(truly_best)
    metadata = json.loads((tmp_path / "run" / "export" / METADATA_NAME).read_text())
    assert metadata["source_checkpoint"]["path"] == str(truly_best.resolve())


def test_the_best_files_are_set_through_lightnings_public_checkpoint_state(tmp_path):
    """Issue 32: the resume's bookkeeping (fastflow3d.training.callbacks.set_best_checkpoints) sets a ModelCheckpoint's
    best files through its public state_dict / load_state_dict, the keys BEST_STATE_KEYS; this fails if a Lightning
    version renames them or stops restoring them."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    from fastflow3d.training.callbacks import BEST_STATE_KEYS, set_best_checkpoints

    def checkpoint_callback():
        return ModelCheckpoint(dirpath=tmp_path, filename="best-{step}", monitor="val/epe", save_top_k=2)

    callback = checkpoint_callback()
    assert set(BEST_STATE_KEYS) <= set(callback.state_dict())
    a, b = str(tmp_path / "best-step=2.ckpt"), str(tmp_path / "best-step=4.ckpt")
    set_best_checkpoints(callback, [(a, 0.1), (b, 0.2)])
    restored = checkpoint_callback()
    restored.load_state_dict(callback.state_dict())  # what a resume from this state sees
    for state in (callback, restored):
        assert {path: round(float(score), 6) for path, score in state.best_k_models.items()} == {a: 0.1, b: 0.2}
        assert (state.best_model_path, round(float(state.best_model_score), 6)) == (a, 0.1)
        assert (state.kth_best_model_path, round(float(state.kth_value), 6)) == (b, 0.2)
    set_best_checkpoints(callback, [])
    assert callback.best_k_models == {} and callback.best_model_path == a


# ------------------------------------------------------------------------------------------- 2. SIGTERM, SIGINT


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_saves_last_checkpoint_at_the_current_step_and_says_how_to_resume(shards, tmp_path, sig):
    """Issue 20.2: SIGTERM to train.py (a scheduler's pre-emption) or Ctrl-C (SIGINT to its process group, the
    DataLoader workers included): last.ckpt at the step it stopped at, one line saying how to resume, exit 143 /
    130, no process left; the resume continues from that step."""
    out = tmp_path / "run"
    process = _popen(_train(out, shards, "trainer.max_steps=100000", "data.workers=2", *STEPS), tmp_path)
    last = out / "checkpoints" / "last.ckpt"
    deadline = time.monotonic() + 300
    while not last.exists():  # the first validation (step 2) is done: the training loop runs
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()[1][-3000:]
        time.sleep(0.05)
    if sig == signal.SIGINT:
        os.killpg(process.pid, sig)  # Ctrl-C reaches the whole foreground group
    else:
        process.send_signal(sig)  # the main process only, as a scheduler does
    _, err = process.communicate(timeout=120)
    assert process.returncode == 128 + sig, err[-3000:]
    assert none_left_within(process.pid), "a process of the run outlived it"
    assert "Traceback" not in err
    words = "terminated (SIGTERM)" if sig == signal.SIGTERM else "interrupted (SIGINT)"
    (line,) = _lines(err, "train")
    match = re.fullmatch(
        rf"train: {re.escape(words)} at step (\d+): saved {re.escape(str(last))}; "
        r"to resume, rerun the same command with ckpt_path=last",
        line,
    )
    assert match, line
    step = int(match.group(1))
    assert step >= 2 and torch.load(last, weights_only=True, mmap=True)["global_step"] == step
    assert _no_temporary_files(out)
    if sig == signal.SIGINT:
        return
    trainer = fit(train_cfg(tmp_path, shards, shards, f"trainer.max_steps={step + 2}", "ckpt_path=last", *STEPS))
    assert trainer.global_step == step + 2
    assert torch.load(last, weights_only=True, mmap=True)["global_step"] == step + 2
    assert len(list(last.parent.glob("best-*.ckpt"))) == 1


# ------------------------------------------------------------------------------------------------ 3. full disk


@pytest.fixture(scope="module")
def checkpoint(shards, tmp_path_factory):
    """A tiny trained checkpoint in <run>/checkpoints (2 steps)."""
    root = tmp_path_factory.mktemp("trained")
    fit(train_cfg(root, shards, shards, "trainer.max_steps=2", *STEPS))
    return root / "run" / "checkpoints" / "last.ckpt"


def _snapshot(folder: Path) -> dict:
    return {path.name: sha256_file(path) for path in sorted(folder.iterdir())}


def test_export_is_built_aside_and_swapped_in_whole(checkpoint, tmp_path, monkeypatch):
    """Issue 20.3 (injected ENOSPC) and issue 21.5: export.py's default folder is the run's export/ (where training
    writes); an export that fails on a full disk leaves the existing one exactly as it was (it used to delete its
    metadata.json), names the file in its final place, and leaves no temporary folder; a successful one replaces
    the folder whole."""
    export = export_checkpoint(checkpoint, formats=("pt2",))
    assert export == checkpoint.parent.parent / "export"  # <run>/export, not <run>/checkpoints/export
    before = _snapshot(export)
    fail_fsync_after(monkeypatch, 0)
    with pytest.raises(WriteError) as error:
        export_checkpoint(checkpoint, formats=("pt2",))
    monkeypatch.undo()
    assert str(error.value) == f"{export / FILE_NAMES['pt2']}: cannot write (No space left on device)"
    assert _snapshot(export) == before and _no_temporary_files(export.parent)
    (export / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match=r"export: holds other files than an export \(notes.txt\)"):
        export_checkpoint(checkpoint, formats=("pt2",))
    (export / "notes.txt").unlink()
    (export / "fastflow3d.pt").write_bytes(b"an older export's TorchScript file")
    export_checkpoint(checkpoint, formats=("pt2",))
    assert sorted(p.name for p in export.iterdir()) == [FILE_NAMES["pt2"], METADATA_NAME]


@pytest.mark.slow
def test_export_on_a_real_full_disk_keeps_the_existing_export(checkpoint, tmp_path, mount_tmpfs):
    """Issue 20.3 on a real tmpfs that holds one export but not two: export.py over the existing export. It used to
    abort (SIGABRT in torch's file writer) and delete metadata.json; now one line, exit 2, the export intact."""
    out = tmp_path / "export"
    export_checkpoint(checkpoint, out, formats=("pt2",))
    size = sum(path.stat().st_size for path in out.iterdir())
    disk = mount_tmpfs(tmp_path / "disk", f"{size * 3 // 2 // 1024}k")
    out = Path(shutil.copytree(out, disk / "export"))
    before = _snapshot(out)
    args = [sys.executable, str(REPO / "export.py"), f"checkpoint={checkpoint}", f"out_dir={out}", "format=pt2"]
    process = _popen(args, tmp_path)
    _, err = process.communicate(timeout=300)
    assert process.returncode == 2, err[-3000:]
    (line,) = _lines(err, "export")
    assert re.fullmatch(
        rf"export: {re.escape(str(out))}/fastflow3d\.pt2: cannot write \(No space left on device\); "
        r"free space there or write elsewhere; the export there is as it was",
        line,
    ), line
    assert _snapshot(out) == before and _no_temporary_files(disk) and none_left_within(process.pid)


def test_a_full_disk_during_training_is_one_line_and_keeps_last_checkpoint(shards, tmp_path, monkeypatch):
    """Issue 20.6 (injected ENOSPC): the checkpoints of step 2 are written (best, then last: 2 fsyncs each), the
    disk is full at step 4: one line naming the file and how to resume; last.ckpt of step 2 is intact."""
    fail_fsync_after(monkeypatch, 4)
    with pytest.raises(TrainError) as error:
        fit(train_cfg(tmp_path, shards, shards, "trainer.max_steps=6", *STEPS))
    monkeypatch.undo()
    checkpoints = tmp_path / "run" / "checkpoints"
    last = checkpoints / "last.ckpt"
    assert re.fullmatch(
        rf"{re.escape(str(checkpoints))}/(best-step0000004-.*|last)\.ckpt: cannot write \(No space left on device\); "
        rf"free space there or write elsewhere; then resume with ckpt_path=last \({re.escape(str(last))} is kept\)",
        str(error.value),
    ), str(error.value)
    assert torch.load(last, weights_only=True)["global_step"] == 2 and _no_temporary_files(tmp_path)


@pytest.mark.slow
def test_train_on_a_real_full_disk_is_one_line_and_keeps_last_checkpoint(shards, checkpoint, tmp_path, mount_tmpfs):
    """Issue 20.6 on a real tmpfs of 2.5 checkpoints of the tiny network: two fit, a third does not."""
    out = mount_tmpfs(tmp_path / "disk", f"{checkpoint.stat().st_size * 5 // 2 // 1024}k") / "run"
    process = _popen(_train(out, shards, "trainer.max_steps=8", *STEPS), tmp_path)
    _, err = process.communicate(timeout=300)
    assert process.returncode == 2, err[-3000:]
    assert "Traceback" not in err and none_left_within(process.pid)
    (line,) = _lines(err, "train")
    last = out / "checkpoints" / "last.ckpt"
    assert line.startswith(f"train: {out / 'checkpoints'}/") and "cannot write (No space left on device)" in line
    assert line.endswith(f"then resume with ckpt_path=last ({last} is kept)"), line
    assert torch.load(last, weights_only=True)["global_step"] >= 2 and _no_temporary_files(out)


# -------------------------------------------------------------------------------------------- 6. one-line errors


HELP = "; see `--help` and `--cfg job` for the options"


@pytest.mark.slow
def test_wrong_types_and_options_are_one_line_naming_the_option(shards, tmp_path):
    """Issue 20.6: a value of the wrong type (train.py, eval.py), a missing checkpoint (export.py): exit 2, one line,
    before any work, as each script prints it; HYDRA_FULL_ERROR=1 gives the traceback."""
    run = ["trainer.max_steps=1", *STEPS]
    defaults = compose_train(*TINY, *run)  # the values before the bad override, as the messages quote them
    cases = {
        "data.batch_size": (
            _train(tmp_path / "a", shards, *run, "data.batch_size=abc"),
            f"train: data.batch_size=abc: expected an integer, got 'abc' (the default is {defaults.data.batch_size})"
            f"{HELP}",
        ),
        "eval limit": (
            [sys.executable, str(REPO / "eval.py"), "limit=abc", f"out_dir={tmp_path / 'e'}"],
            f"eval: limit=abc: expected an integer, got 'abc'{HELP}",
        ),
        "export": (
            [sys.executable, str(REPO / "export.py"), f"checkpoint={tmp_path / 'none.ckpt'}"],
            f"export: {tmp_path / 'none.ckpt'}: checkpoint not found",
        ),
    }
    processes = {name: _popen(args, tmp_path) for name, (args, _) in cases.items()}
    for name, process in processes.items():
        _, err = process.communicate(timeout=300)
        assert (process.returncode, err.strip()) == (2, cases[name][1]), name
        assert none_left_within(process.pid)
    assert not (tmp_path / "a").exists()  # refused while composing, before any work: not even Hydra's record
    # (the lines of other wrong types and unknown options: tests/icpflow/core/test_settings.py, in this process)
    full = subprocess.run(
        _train(tmp_path / "f", shards, *run, "data.batch_size=abc"),
        env={**TESTS_ENV, "HYDRA_FULL_ERROR": "1"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert full.returncode == 1 and "Traceback" in full.stderr
    assert "Error merging override data.batch_size=abc" in full.stderr


@pytest.mark.slow
def test_a_read_only_out_dir_is_one_line(shards, tmp_path, mount_tmpfs):
    """Issue 20.6: train.py with a read-only out_dir (it printed 24 lines of traceback from Hydra)."""
    disk = mount_tmpfs(tmp_path / "ro", "1m", read_only=True)
    result = subprocess.run(
        _train(disk / "run", shards, "trainer.max_steps=1", *STEPS), env=TESTS_ENV, capture_output=True, text=True
    )
    assert (result.returncode, result.stderr.strip()) == (
        2,
        f"train: {disk / 'run'}: Read-only file system; write to a writable place",
    )


def test_a_checkpoint_of_another_network_and_a_corrupt_index_are_one_line(shards, checkpoint, tmp_path):
    """Issue 20.6: ckpt_path= a checkpoint of another model size (144 lines of traceback before), a shard folder
    whose index.json is corrupt (17 lines)."""
    with pytest.raises(TrainError) as error:
        fit(train_cfg(tmp_path, shards, shards, f"ckpt_path={checkpoint}", "model.pillar_channels=8"))
    assert str(error.value) == (
        f"ckpt_path={checkpoint}: {checkpoint} holds another network: model.pillar_channels=16 (this run: 8); "
        "resume with the model settings it was trained with, or leave ckpt_path unset to start afresh"
    )
    broken = tmp_path / "broken"
    shutil.copytree(shards, broken)
    (broken / "index.json").write_text('{"shards": [')
    with pytest.raises(TrainError) as error:
        fit(train_cfg(tmp_path, broken, shards, "trainer.fast_dev_run=true"))
    message = str(error.value)
    assert "\n" not in message and message.startswith(f"data.train: {broken / 'index.json'}: not a labelling index")
    assert message.endswith(f"rerun the label.py command that wrote it (same out_dir={broken}): it rebuilds the index")


# --------------------------------------------------------------------------------------- 8. infer, read-only --out


def test_infer_on_a_read_only_place_names_the_users_file(checkpoint, tmp_path, mount_tmpfs, capsys):
    """Issue 20.8: --out on a read-only filesystem named an internal .tmp-... file; now the file asked for."""
    pair = SyntheticDataset(**READER).pair(0)
    scans = [tmp_path / "scan0.npy", tmp_path / "scan1.npy"]
    np.save(scans[0], pair.pc0)
    np.save(scans[1], pair.pc1)
    ego = tmp_path / "ego.txt"
    np.savetxt(ego, pair.ego1_from_ego0.reshape(1, 16))
    disk = mount_tmpfs(tmp_path / "ro", "1m", read_only=True)
    for out in (disk / "flow.npz", disk / "new" / "flow.npz"):
        status = infer_main([str(checkpoint), *map(str, scans), "--ego", str(ego), "--out", str(out), "--no-bev"])
        err = capsys.readouterr().err.strip()
        assert (status, err) == (2, f"infer: {out}: cannot write (Read-only file system); write to a writable place")
