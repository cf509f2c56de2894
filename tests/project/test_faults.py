"""Real faults, each reproduced on a small synthetic input: the run says what happened in one line naming the file
or the out_dir, keeps every finished piece of work, leaves no process behind, and a rerun completes the job."""

import json
import logging
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from fastflow3d.inference.cli import main as infer_main
from fastflow3d.inference.prediction import PredictorError
from fastflow3d.inference.predictor import Predictor
from fastflow3d.inference.scan_files import read_raw_scan
from fastflow3d.training.run_folder import TrainError
from fastflow3d.training.trainer import fit
from icpflow.core.frame_pair import FramePairError
from icpflow.datasets.file_formats import load_npz
from icpflow.datasets.scan_folder import ScanSequenceDataset
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.labelling.cli import label
from icpflow.shards import ShardDataset, verify_shard
from icpflow.teacher import ICPFlow

from helpers.disk import fail_fsync_after
from helpers.labelling import (
    RERUN_ENV,
    SUMMARY,
    TESTS_ENV,
    all_valid,
    assert_same,
    label_cfg,
    label_script,
    none_left_within,
)
from helpers.shards import write_pseudo_labels
from helpers.training import train_cfg

SLOW = ["dataset.reader._target_=helpers.labelling.SlowSynthetic", "workers=2"]
READER = {"split": "train", "num_sequences": 1, "frames_per_sequence": 3, "beams": 32, "azimuth_resolution_deg": 2.0}


def _start(out_dir, *overrides) -> subprocess.Popen:
    """label.py in its own session (process group = its pid), once its first shard is recorded."""
    process = subprocess.Popen(
        label_script(out_dir, *overrides),
        cwd=out_dir.parent,
        env=TESTS_ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    deadline = time.monotonic() + 600
    while not (out_dir / "shard_000000.h5.json").exists():
        assert process.poll() is None and time.monotonic() < deadline, process.stderr.read() if process.poll() else ""
        time.sleep(0.05)
    return process


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_killing_the_main_process_ends_its_workers(reference, tmp_path, sig):
    """SIGKILL or SIGTERM to label.py's main process only (as a supervisor or a job scheduler sends it) while its 2
    workers label: no process outlives it, whatever has a final name is complete (SIGTERM: exit 143, one line, the
    index lists exactly the complete shards, no temporary file); the rerun of the same command labels the rest and
    matches the uninterrupted run."""
    out = tmp_path / "labels"
    out.mkdir()
    process = _start(out, *SLOW)
    time.sleep(0.5)  # both workers busy in their slow shards
    process.send_signal(sig)  # the main process only, as a supervisor or a job scheduler does
    _, err = process.communicate(timeout=60)
    assert none_left_within(process.pid, 5), "a process of the run outlived it"
    if sig == signal.SIGTERM:
        assert process.returncode == 143, err
        assert err.strip().splitlines()[-1] == (
            f"label: terminated (SIGTERM); complete shards are kept in {out}, rerun the same command to resume"
        )
        assert "Traceback" not in err
        assert all_valid(out) >= 2  # index.json lists exactly the complete shards on disk
        indexed = {s["file"] for s in json.loads((out / "index.json").read_text())["shards"]}
        assert indexed == {p.name for p in out.glob("shard_*.h5")}
        assert not list(out.glob("*.tmp-*"))
    else:
        assert process.returncode == -signal.SIGKILL
    for shard in out.glob("shard_*.h5"):  # whatever has a final name is complete
        verify_shard(shard)
    run = subprocess.run(label_script(out, *SLOW), cwd=tmp_path, env=RERUN_ENV, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    done, skipped = map(int, SUMMARY.search(run.stdout).groups()[:2])
    assert skipped >= 2 and done + skipped == 5
    assert all_valid(out) == 5
    assert_same(reference, out)


class KillOnceSynthetic(SyntheticDataset):
    """Sample 3 kills its worker once (a transient death: the out-of-memory killer), marked by file ``marker``."""

    def __init__(self, marker, **kwargs):
        super().__init__(**kwargs)
        self.marker = Path(marker)

    def pair(self, index, horizon=1):
        if index == 3 and not self.marker.exists():
            self.marker.touch()
            os.kill(os.getpid(), signal.SIGKILL)
        return super().pair(index, horizon)


@pytest.mark.slow
def test_a_sample_whose_worker_died_is_filled_in_by_the_rerun(reference, tmp_path, capsys):
    cfg = label_cfg(
        tmp_path / "labels",
        f"dataset.reader._target_={__name__}.KillOnceSynthetic",
        f"+dataset.reader.marker={tmp_path / 'killed'}",
        "workers=2",
    )
    assert label(cfg, progress=False) == 1
    assert (tmp_path / "killed").exists()
    failures = (tmp_path / "labels" / "failures.jsonl").read_text().splitlines()
    assert [json.loads(line)["index"] for line in failures] == [3]
    capsys.readouterr()
    cfg.workers = 1  # the rerun in this process: what it fills in does not depend on the workers
    assert label(cfg, progress=False) == 0
    assert SUMMARY.fullmatch(capsys.readouterr().out.strip()).groups()[:3] == ("1", "4", "0")
    assert (tmp_path / "labels" / "failures.jsonl").read_text() == ""  # only what failed in the latest run
    assert_same(reference, tmp_path / "labels")


class FixedLaterSynthetic(SyntheticDataset):
    """Sample 1 cannot be read while file ``broken`` exists (a bad input file, fixed by the user later)."""

    def __init__(self, broken, **kwargs):
        super().__init__(**kwargs)
        self.broken = Path(broken)

    def pair(self, index, horizon=1):
        if index == 1 and self.broken.exists():
            from icpflow.datasets.file_formats import fail

            raise fail(self.broken, "truncated")
        return super().pair(index, horizon)


def test_a_fixed_input_is_labelled_by_the_rerun(reference, tmp_path, capsys):
    broken = tmp_path / "000001.bin"
    broken.touch()
    cfg = label_cfg(
        tmp_path / "labels",
        f"dataset.reader._target_={__name__}.FixedLaterSynthetic",
        f"+dataset.reader.broken={broken}",
    )
    assert label(cfg, progress=False) == 1
    assert f"failed synthetic-train-0-32b/000001+1 ({broken})" in capsys.readouterr().err
    broken.unlink()  # the user fixes the input
    assert label(cfg, progress=False) == 0
    assert SUMMARY.fullmatch(capsys.readouterr().out.strip()).groups()[:3] == ("1", "4", "0")
    assert_same(reference, tmp_path / "labels")


def test_a_full_disk_is_one_line_and_keeps_the_finished_shards(reference, tmp_path, monkeypatch, capsys):
    out = tmp_path / "labels"
    # config.yaml, then shard 0 and its record (each file: its own fsync and its folder's), then shard 1 fails
    fail_fsync_after(monkeypatch, 6)
    assert label(label_cfg(out), progress=False) == 2
    err = capsys.readouterr().err
    assert err == (
        f"label: {out / 'shard_000001.h5'}: cannot write (No space left on device); complete shards are "
        f"kept in {out}, fix this and rerun the same command to resume\n"
    )
    assert sorted(p.name for p in out.iterdir()) == ["config.yaml", "shard_000000.h5", "shard_000000.h5.json"]
    monkeypatch.undo()  # space is freed
    assert label(label_cfg(out), progress=False) == 0
    assert "3 samples labelled, 2 skipped" in capsys.readouterr().out
    assert_same(reference, out)


@pytest.mark.slow
def test_a_full_disk_while_workers_run_is_one_line_and_leaves_no_process(tmp_path):
    out = tmp_path / "labels"
    args = ["dataset.reader._target_=helpers.readers.DiskFullSynthetic", "workers=2", "shard_size=3"]
    process = subprocess.Popen(
        label_script(out, *args),
        cwd=tmp_path,
        env=TESTS_ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    _, err = process.communicate(timeout=600)  # generous: a loaded CI machine
    assert process.returncode == 2, err
    assert [line for line in err.splitlines() if line and not line.startswith("labelling")] == [
        f"label: {out / 'shard_000000.h5'}: cannot write (No space left on device); "
        f"complete shards are kept in {out}, fix this and rerun the same command "
        "to resume"
    ]
    assert none_left_within(process.pid, 5)
    assert not list(out.glob("*.tmp-*"))
    assert json.loads((out / "index.json").read_text())["shards"] == [
        {"file": p.name, "samples": json.loads((out / f"{p.name}.json").read_text())["samples"]}
        for p in sorted(out.glob("shard_*.h5"))
    ]
    assert len(ShardDataset(out)) in (0, 2)  # shard 1 (samples 3, 4) may have finished first
    assert np.all([verify_shard(p) for p in out.glob("shard_*.h5")])


# ------------------------------------------------------------------------------------------- malformed point input


@pytest.fixture(scope="module")
def scan():
    return SyntheticDataset(**READER).pair(0).pc0


def _infer(args, capsys) -> tuple[int, list[str]]:
    status = infer_main([*map(str, args), "--no-bev"])
    return status, capsys.readouterr().err.splitlines()


def test_every_malformed_point_file_is_one_line_naming_it(scan, tiny_student, tmp_path, capsys):
    good = tmp_path / "good.npy"
    np.save(good, scan)
    cases = {
        "transposed.npy": (lambda path: np.save(path, scan.T), "scan has shape (3, "),
        "transposed.npz": (lambda path: np.savez(path, points=scan.T), "points has shape (3, "),
        "text.npz": (lambda path: path.write_text("x y z\n1 2 3\n"), "not an .npz file"),
        "nan.npy": (lambda path: np.save(path, np.vstack([scan, [[np.nan, 0, 0]]])), "scan has 1 rows with NaN"),
        "xyz.bin": (lambda path: scan.tofile(path), "give its column count (bin_columns=N, --bin-columns N)"),
        "flat.npy": (lambda path: np.save(path, scan[:, :2]), "scan must be a numeric (N, 3) array"),
    }
    for name, (make, message) in cases.items():
        path = tmp_path / name
        make(path)
        status, err = _infer([tiny_student, path, good, "--out", tmp_path / "flow.npz"], capsys)
        assert status == 2 and len(err) == 1, err
        assert err[0].startswith(f"infer: {path}: ") and message in err[0], err
    assert not (tmp_path / "flow.npz").exists()
    np.testing.assert_array_equal(read_raw_scan(tmp_path / "xyz.bin", bin_columns=3), scan)  # explicit layout


def test_the_same_rule_in_the_readers_the_predictor_and_the_teacher(scan, tiny_student, tmp_path):
    folder = tmp_path / "drive"
    folder.mkdir()
    np.save(folder / "0.npy", scan)
    np.save(folder / "1.npy", scan.T)
    with pytest.raises(FramePairError, match=r"1.npy: scan has shape \(3, \d+\): a transposed scan\?"):
        ScanSequenceDataset(folder).pair(0)
    whole = scan[: len(scan) // 4 * 4]  # x, y, z rows whose size is also a whole number of x, y, z, r rows
    for name in ("0", "1"):
        whole.tofile(folder / f"{name}.bin")
        (folder / f"{name}.npy").unlink()
    with pytest.raises(FramePairError, match=r"0.bin: values are implausible for float32 rows of x, y, z, r"):
        ScanSequenceDataset(folder).pair(0)
    np.testing.assert_array_equal(ScanSequenceDataset(folder, bin_columns=3).pair(0).pc0, whole)
    (tmp_path / "notes.npz").write_text("not a zip")
    with pytest.raises(FramePairError, match="notes.npz: not an .npz file"):
        load_npz(tmp_path / "notes.npz", ("pc0",))
    with pytest.raises(PredictorError, match=r"Predictor: pc0 has shape \(3, \d+\): a transposed scan\?"):
        Predictor.load(tiny_student)(scan.T, scan, np.eye(4))
    with pytest.raises(ValueError, match=r"ICPFlow: pc1 has shape \(3, \d+\): a transposed scan\?"):
        ICPFlow()(scan, scan.T, np.eye(4))


def test_integer_coordinates_are_read_with_a_warning(scan, tmp_path, caplog):
    path = tmp_path / "ints.npy"
    np.save(path, np.round(scan).astype(np.int32))
    with caplog.at_level(logging.WARNING, logger="icpflow.core.frame_pair"):
        points = read_raw_scan(path)
    assert points.dtype == np.float32 and np.array_equal(points, np.round(scan))
    assert [r.getMessage() for r in caplog.records] == [
        f"{path}: scan has int32 coordinates, read as metres: whole metres only"
    ]


def test_a_scan_outside_the_grid_gets_a_warning(scan, tiny_student, tmp_path, capsys):
    far = scan + np.float32(1000.0)  # metres away from the sensor: millimetres read as metres, say
    np.save(tmp_path / "far0.npy", far)
    np.save(tmp_path / "far1.npy", far)
    np.savetxt(tmp_path / "ego.txt", np.eye(4).reshape(1, 16))
    status, err = _infer(
        [
            tiny_student,
            tmp_path / "far0.npy",
            tmp_path / "far1.npy",
            "--ego",
            tmp_path / "ego.txt",
            "--out",
            tmp_path / "flow.npz",
        ],
        capsys,
    )
    assert (
        status == 0
        and len(err) == 1
        and err[0].startswith(f"infer: warning: no point of {tmp_path / 'far0.npy'} lies inside the model's grid")
    )


# ------------------------------------------------------------------------------------------------ training data


@pytest.fixture(scope="module")
def pairs():
    return [SyntheticDataset(**READER).pair(0)]


def test_a_corrupt_shard_stops_training_in_one_line_naming_it(pairs, tmp_path):
    good, bad = write_pseudo_labels(tmp_path / "good", pairs), write_pseudo_labels(tmp_path / "bad", pairs)
    shard = bad / "shard_000000.h5"
    shard.write_bytes(shard.read_bytes()[: shard.stat().st_size // 2])
    with pytest.raises(TrainError) as error:
        fit(train_cfg(tmp_path, good, bad, "trainer.fast_dev_run=true"))
    message = str(error.value)
    assert "\n" not in message and message.startswith(f"data.val: {shard}: unreadable")
    assert message.endswith(f"rerun the label.py command that wrote it (same out_dir={bad}): it redoes damaged shards")


def test_a_truncated_checkpoint_is_one_line_naming_it(pairs, tiny_student, tmp_path):
    good = write_pseudo_labels(tmp_path / "good", pairs)
    truncated = tmp_path / "last.ckpt"
    truncated.write_bytes(tiny_student.read_bytes()[:2000])
    with pytest.raises(TrainError) as error:
        fit(train_cfg(tmp_path, good, good, f"ckpt_path={truncated}"))
    message = str(error.value)
    assert "\n" not in message and message.startswith(
        f"ckpt_path={truncated}: {truncated}: not a readable torch checkpoint, truncated or damaged?"
    )
    foreign = tmp_path / "foreign.ckpt"
    torch.save({"state_dict": {}, "when": np.datetime64("2026-01-01")}, foreign)  # not loadable with weights_only
    with pytest.raises(TrainError) as error:
        fit(train_cfg(tmp_path, good, good, f"ckpt_path={foreign}"))
    assert "weights_only" not in str(error.value) and "\n" not in str(error.value)
    assert "it holds objects other than tensors and plain data" in str(error.value)


class UnreadableSynthetic(SyntheticDataset):
    """Every sample's file is damaged (the reader fails before the teacher runs)."""

    def pair(self, index, horizon=1):
        from icpflow.datasets.file_formats import fail

        raise fail(f"/data/{index:06d}.bin", "truncated")


def test_the_summary_says_how_many_failures_it_does_not_list(tmp_path, capsys):
    cfg = label_cfg(
        tmp_path,
        f"dataset.reader._target_={__name__}.UnreadableSynthetic",
        "dataset.reader.frames_per_sequence=15",
        "limit=14",
        "shard_size=7",
    )
    assert label(cfg, progress=False) == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 11 and err[9].startswith("  failed synthetic-train-0-32b/000009+1 (/data/000009.bin)")
    assert err[10] == f"  ... and 4 more (all in {tmp_path / 'failures.jsonl'})"
    assert len((tmp_path / "failures.jsonl").read_text().splitlines()) == 14


def test_a_bin_scan_in_another_dtype_or_unit_is_refused_whatever_the_column_count(scan, tiny_student, tmp_path, capsys):
    """Issue 45.8: float64 rows read as the float32 rows the column count says gave points of 1e19 m (the range
    check was skipped with --bin-columns); a scan in millimetres or centimetres is told so, not asked for a column
    count. Each is one line naming the file, exit 2, for every column count."""
    good = tmp_path / "good.npy"
    np.save(good, scan)
    doubles = tmp_path / "doubles.bin"
    np.column_stack([scan, np.ones(len(scan))]).astype(np.float64).tofile(doubles)
    for columns in ([], ["--bin-columns", "4"], ["--bin-columns", "8"]):
        status, err = _infer([tiny_student, doubles, good, "--out", tmp_path / "flow.npz", *columns], capsys)
        assert status == 2 and len(err) == 1 and "values are implausible for float32 rows" in err[0], err
    for unit, factor in (("millimetres", 1000), ("centimetres", 100)):
        path = tmp_path / f"{unit}.bin"
        np.column_stack([scan * factor, np.ones(len(scan))]).astype(np.float32).tofile(path)
        for columns in ([], ["--bin-columns", "4"]):
            status, err = _infer([tiny_student, path, good, "--out", tmp_path / "flow.npz", *columns], capsys)
            assert status == 2 and len(err) == 1 and f"the coordinates look like {unit}" in err[0], err
    assert not (tmp_path / "flow.npz").exists()
