"""Real faults, each reproduced on a small synthetic input: the run says what happened in one line naming the file
or the out_dir, keeps every finished piece of work, leaves no process behind, and a rerun completes the job."""

import errno
import json
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from test_label import SUMMARY, TESTS_ENV, _all_valid, _assert_same, _cfg, _running_in_group, _script
from test_label import reference  # noqa: F401  (the module-scoped fixture: an uninterrupted run)

from icpflow.datasets.synthetic import SyntheticDataset
from icpflow.labelling.cli import label
from icpflow.shards import ShardDataset, verify_shard
from icpflow.shards import writer

SLOW = ["dataset.reader._target_=test_label.SlowSynthetic", "workers=2"]


def _start(out_dir, *overrides) -> subprocess.Popen:
    """label.py in its own session (process group = its pid), once its first shard is recorded."""
    process = subprocess.Popen(_script(out_dir, *overrides), cwd=out_dir.parent, env=TESTS_ENV,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 120
    while not (out_dir / "shard_000000.h5.json").exists():
        assert process.poll() is None and time.monotonic() < deadline, process.stderr.read() if process.poll() else ""
        time.sleep(0.05)
    return process


def _none_left_within(group: int, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while _running_in_group(group):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_killing_the_main_process_ends_its_workers(reference, tmp_path, sig):
    out = tmp_path / "labels"
    out.mkdir()
    process = _start(out, *SLOW)
    time.sleep(0.5)  # both workers busy in their slow shards
    process.send_signal(sig)  # the main process only, as a supervisor or a job scheduler does
    _, err = process.communicate(timeout=60)
    assert _none_left_within(process.pid, 5), "a process of the run outlived it"
    if sig == signal.SIGTERM:
        assert process.returncode == 143, err
        assert err.strip().splitlines()[-1] == (f"label: terminated (SIGTERM); complete shards are kept in {out}, "
                                                "rerun the same command to resume")
        assert "Traceback" not in err
        assert _all_valid(out) >= 2  # index.json lists exactly the complete shards on disk
        indexed = {s["file"] for s in json.loads((out / "index.json").read_text())["shards"]}
        assert indexed == {p.name for p in out.glob("shard_*.h5")}
    else:
        assert process.returncode == -signal.SIGKILL
    assert not list(out.glob("*.tmp-*")) or sig == signal.SIGKILL
    for shard in out.glob("shard_*.h5"):  # whatever has a final name is complete
        verify_shard(shard)
    run = subprocess.run(_script(out, *SLOW), cwd=tmp_path, env=TESTS_ENV, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    done, skipped = map(int, SUMMARY.search(run.stdout).groups()[:2])
    assert skipped >= 2 and done + skipped == 5
    _assert_same(reference, out)


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


def test_a_sample_whose_worker_died_is_filled_in_by_the_rerun(reference, tmp_path, capsys):
    cfg = _cfg(tmp_path / "labels", f"dataset.reader._target_={__name__}.KillOnceSynthetic",
               f"+dataset.reader.marker={tmp_path / 'killed'}", "workers=2")
    assert label(cfg, progress=False) == 1
    assert (tmp_path / "killed").exists()
    failures = (tmp_path / "labels" / "failures.jsonl").read_text().splitlines()
    assert [json.loads(line)["index"] for line in failures] == [3]
    capsys.readouterr()
    assert label(cfg, progress=False) == 0
    assert SUMMARY.fullmatch(capsys.readouterr().out.strip()).groups()[:3] == ("1", "4", "0")
    assert (tmp_path / "labels" / "failures.jsonl").read_text() == ""  # only what failed in the latest run
    _assert_same(reference, tmp_path / "labels")


class FixedLaterSynthetic(SyntheticDataset):
    """Sample 1 cannot be read while file ``broken`` exists (a bad input file, fixed by the user later)."""

    def __init__(self, broken, **kwargs):
        super().__init__(**kwargs)
        self.broken = Path(broken)

    def pair(self, index, horizon=1):
        if index == 1 and self.broken.exists():
            from icpflow.datasets.io import fail

            raise fail(self.broken, "truncated")
        return super().pair(index, horizon)


def test_a_fixed_input_is_labelled_by_the_rerun(reference, tmp_path, capsys):
    broken = tmp_path / "000001.bin"
    broken.touch()
    cfg = _cfg(tmp_path / "labels", f"dataset.reader._target_={__name__}.FixedLaterSynthetic",
               f"+dataset.reader.broken={broken}")
    assert label(cfg, progress=False) == 1
    assert f"failed synthetic-train-0-32b/000001+1 ({broken})" in capsys.readouterr().err
    broken.unlink()  # the user fixes the input
    assert label(cfg, progress=False) == 0
    assert SUMMARY.fullmatch(capsys.readouterr().out.strip()).groups()[:3] == ("1", "4", "0")
    _assert_same(reference, tmp_path / "labels")


def _disk_full_after(monkeypatch, writes: int) -> None:
    """Make every fsync after the first ``writes`` fail with ENOSPC, as on a full disk."""
    real, count = os.fsync, [0]

    def fsync(fd):
        count[0] += 1
        if count[0] > writes:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(fd)

    monkeypatch.setattr(writer.os, "fsync", fsync)


def test_a_full_disk_is_one_line_and_keeps_the_finished_shards(reference, tmp_path, monkeypatch, capsys):
    out = tmp_path / "labels"
    # config.yaml, then shard 0 and its record (each file: its own fsync and its folder's), then shard 1 fails
    _disk_full_after(monkeypatch, 6)
    assert label(_cfg(out), progress=False) == 2
    err = capsys.readouterr().err
    assert err == (f"label: {out / 'shard_000001.h5'}: cannot write (No space left on device); complete shards are "
                   f"kept in {out}, fix this and rerun the same command to resume\n")
    assert sorted(p.name for p in out.iterdir()) == ["config.yaml", "shard_000000.h5", "shard_000000.h5.json"]
    monkeypatch.undo()  # space is freed
    assert label(_cfg(out), progress=False) == 0
    assert "3 samples labelled, 2 skipped" in capsys.readouterr().out
    _assert_same(reference, out)


class DiskFullSynthetic(SyntheticDataset):
    """The small world in a worker whose disk is full from its first write on (sample 2's shard)."""

    def pair(self, index, horizon=1):
        if index == 2:
            def full(fd):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

            writer.os.fsync = full  # in this worker process only
        return super().pair(index, horizon)


def test_a_full_disk_in_a_worker_is_one_line_and_leaves_no_process(tmp_path):
    out = tmp_path / "labels"
    args = ["dataset.reader._target_=test_faults.DiskFullSynthetic", "workers=2", "shard_size=3"]
    process = subprocess.Popen(_script(out, *args), cwd=tmp_path, env=TESTS_ENV, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, start_new_session=True)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 2, err
    assert [line for line in err.splitlines() if line and not line.startswith("labelling")] == [f"label: {out / 'shard_000000.h5'}: cannot write (No space left on device); "
                                        f"complete shards are kept in {out}, fix this and rerun the same command "
                                        "to resume"]
    assert _none_left_within(process.pid, 5)
    assert not list(out.glob("*.tmp-*"))
    assert json.loads((out / "index.json").read_text())["shards"] == [
        {"file": p.name, "samples": json.loads((out / f"{p.name}.json").read_text())["samples"]}
        for p in sorted(out.glob("shard_*.h5"))]
    assert len(ShardDataset(out)) in (0, 2)  # shard 1 (samples 3, 4) may have finished first
    assert np.all([verify_shard(p) for p in out.glob("shard_*.h5")])
