"""Faults of eval.py, each reproduced: SIGTERM and Ctrl-C keep the pairs scored (a partial metrics.json that says
so) and leave no process behind; a read-only or full out_dir is one line before any pair is scored; a disk that
fills up during the run is one line at the end and the scores are saved elsewhere. Real signals; a real small tmpfs
where this machine permits mounting one (root), an injected OSError otherwise."""

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.evaluation import method_summary, read_metrics, run_eval
from icpflow.evaluation.baselines import ego_only_flow

from helpers.data import REPO
from helpers.disk import fail_fsync_after
from helpers.labelling import default_sigint, running_in_group

SMALL = [
    "dataset.reader.num_sequences=1",
    "dataset.reader.frames_per_sequence=3",
    "dataset.reader.beams=32",
    "dataset.reader.azimuth_resolution_deg=1.0",
]
#: environment of an eval.py subprocess that can import the readers defined in this file
TESTS_ENV = {
    **os.environ,
    "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO / "tests"), os.environ.get("PYTHONPATH")])),
}


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_stopped_eval_keeps_the_pairs_scored_and_leaves_no_process(tmp_path, sig):
    out, marker = tmp_path / "eval", tmp_path / "second-sample-started"
    process = subprocess.Popen(
        [
            sys.executable,
            str(REPO / "eval.py"),
            *SMALL,
            "dataset.reader._target_=helpers.readers.StallAfterFirst",
            f"+dataset.reader.marker={marker}",
            "method=[ego,icpflow]",
            "bev=0",
            f"out_dir={out}",
            f"hydra.run.dir={tmp_path / 'hydra'}",
        ],
        cwd=tmp_path,
        env=TESTS_ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group: everything it starts is found by the group id
        preexec_fn=default_sigint,  # Ctrl-C as a terminal delivers it, even when pytest runs as a background job
    )
    deadline = time.monotonic() + 600  # generous: a loaded machine
    while not marker.exists():
        assert process.poll() is None and time.monotonic() < deadline, process.communicate()[1]
        time.sleep(0.1)
    helpers = [pid for pid in running_in_group(process.pid) if pid != process.pid]
    assert helpers, "no helper process started: this test would prove nothing"
    if sig == signal.SIGTERM:
        process.send_signal(sig)  # the main process only, as a scheduler does
    else:
        os.killpg(process.pid, sig)  # Ctrl-C: the terminal signals the whole group
    _, err = process.communicate(timeout=120)
    deadline = time.monotonic() + 5
    while running_in_group(process.pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert running_in_group(process.pid) == [], "a process of the run outlived it"
    what, status = ("terminated (SIGTERM)", 143) if sig == signal.SIGTERM else ("interrupted (Ctrl-C)", 130)
    assert process.returncode == status, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == (
        f'eval: {what}; the 1 pairs scored are kept in {out / "metrics.json"} ("complete": false); '
        "rerun the same command for all pairs"
    )
    document = read_metrics(out, partial_ok=True)
    assert document["complete"] is False and document["stopped"] == what
    world = SyntheticDataset(split="val", num_sequences=1, frames_per_sequence=3, beams=32, azimuth_resolution_deg=1.0)
    assert document["pairs"] == {"1": [world.sample_id(0)]}
    assert method_summary(document, "icpflow")["pairs"] == 1
    with pytest.raises(ValueError, match="partial"):
        read_metrics(out)  # readers that want a complete table refuse it
    assert not list(out.glob("*.tmp-*"))


# ---------------------------------------------------------------------------------------------------- out_dir


def _cfg(out_dir, *overrides):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose("eval", [*SMALL, "method=[counted]", "bev=0", f"out_dir={out_dir}", *overrides])


class Counted:
    """The ego baseline as an extra method that counts its calls (and can run ``then`` after its first one)."""

    def __init__(self, then=None):
        self.calls, self.then = 0, then

    def __call__(self, pair, index):
        self.calls += 1
        if self.then is not None and self.calls == 1:
            self.then()
        return ego_only_flow(pair)


def _mount_tmpfs(path: Path, options: str) -> bool:
    """Mount a tmpfs on ``path`` (created); False where this machine does not permit it."""
    path.mkdir(parents=True, exist_ok=True)
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return False
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)], capture_output=True)
    return done.returncode == 0


@pytest.fixture
def tmpfs(tmp_path):
    """``mount(name, options)`` -> a small tmpfs under tmp_path, or None where mounting is not permitted."""
    mounted = []

    def mount(name: str, options: str) -> Path | None:
        path = tmp_path / name
        if _mount_tmpfs(path, options):
            mounted.append(path)
            return path
        return None

    yield mount
    for path in mounted:
        subprocess.run(["umount", str(path)], check=False)


def _fill(folder: Path) -> None:
    """Write into ``folder`` until its filesystem is full."""
    with open(folder / "filler", "ab") as handle:
        try:
            while True:
                handle.write(b"\0" * 65536)
                handle.flush()
                os.fsync(handle.fileno())
        except OSError as error:
            assert error.errno == errno.ENOSPC


@pytest.mark.parametrize("fault", ["read-only", "full"])
def test_an_unwritable_out_dir_is_one_line_before_any_pair_is_scored(tmp_path, tmpfs, monkeypatch, capsys, fault):
    place = tmpfs(fault, "size=1m,ro" if fault == "read-only" else "size=256k")
    code = errno.EROFS if fault == "read-only" else errno.ENOSPC
    if place is None:  # no tmpfs here: the same error, injected
        place = tmp_path / fault
        fail_fsync_after(monkeypatch, 0, code, place)
    elif fault == "full":
        _fill(place)
    method = Counted()
    out = place / "eval"
    assert run_eval(_cfg(out), progress=False, extra_methods={"counted": lambda cfg: method}) == 2
    assert method.calls == 0  # refused before the long work
    assert capsys.readouterr().err == (
        f"eval: out_dir={out}: cannot write there ({os.strerror(code)}); nothing was scored: choose a writable "
        "out_dir=... with free space\n"
    )


def test_a_disk_filling_up_during_the_run_is_one_line_and_the_scores_are_saved_elsewhere(
    tmp_path, tmpfs, monkeypatch, capsys
):
    import tempfile

    spare = tmp_path / "spare"
    spare.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(spare))  # the system's temporary folder, for this test
    place = tmpfs("disk", "size=2m")  # room for the out_dir check, then another job fills it
    if place is None:
        place = tmp_path / "disk"
        method = Counted()
        fail_fsync_after(monkeypatch, 1, errno.ENOSPC, place)  # the out_dir check's fsync passes, the results' fail
    else:
        method = Counted(then=lambda: _fill(place))
    out = place / "eval"
    assert run_eval(_cfg(out), progress=False, extra_methods={"counted": lambda cfg: method}) == 2
    assert method.calls == 2  # every pair was scored
    captured = capsys.readouterr()
    saved = list(spare.glob("eval-metrics-*.json"))
    assert len(saved) == 1
    assert captured.err == (
        f"eval: {out / 'metrics.json'}: cannot write (No space left on device); the scores were saved to {saved[0]} "
        "instead; free space or choose another out_dir=... and rerun\n"
    )
    assert "counted" in captured.out  # the table was printed before
    document = read_metrics(saved[0])
    assert document["complete"] and method_summary(document, "counted")["pairs"] == 2
    assert json.loads(saved[0].read_text())["pairs"]["1"] == document["pairs"]["1"]
    assert not (out / "metrics.json").exists() and not list(out.glob("*.tmp-*"))


def test_a_picture_that_cannot_be_written_is_one_line_and_the_scoring_goes_on(capsys):
    from icpflow.core.atomic import WriteError
    from icpflow.evaluation import MetricOptions, evaluate

    dataset = SyntheticDataset(
        split="val", num_sequences=1, frames_per_sequence=3, beams=32, azimuth_resolution_deg=1.0
    )
    calls = []

    def bev(predictions):
        calls.append(predictions.index)
        raise WriteError(f"bev/{predictions.pair.sample_id}_ego.png: cannot write (No space left on device)")

    method = Counted()
    result = evaluate(dataset, {1: {"ego": method}}, MetricOptions(), hooks=[bev])
    assert calls == [0] and method.calls == len(dataset) == len(result.pairs[1])  # dropped after its first failure
    assert capsys.readouterr().err == (
        f"eval: bev/{dataset.sample_id(0)}_ego.png: cannot write (No space left on device); no more files from bev\n"
    )
