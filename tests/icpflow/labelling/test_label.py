"""The labelling stage end to end: the real teacher on a small synthetic world (32 beams, 2 deg azimuth)."""

import json
import logging
import multiprocessing
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from icpflow.core.threads import available_cores, thread_limit
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.labelling.cli import label
from icpflow.labelling.job import LabelJob
from icpflow.labelling.records import DIED, write_shard_and_record
from icpflow.labelling.sample import label_sample
from icpflow.shards import ShardDataset
from icpflow.teacher import ICPFlow
from icpflow.teacher.config import teacher_config
from icpflow.teacher.long_horizon import long_horizon_flow

from helpers.labelling import (
    READER,
    REPO,
    RERUN_ENV,
    SUMMARY,
    TESTS_ENV,
    all_valid,
    assert_same,
    default_sigint,
    label_cfg,
    label_script,
    read_samples,
    running_in_group,
)


def test_round_trip_holds_reader_input_and_teacher_output(reference):
    assert all_valid(reference) == 5
    assert sorted(p.name for p in reference.glob("shard_*.h5")) == [f"shard_00000{i}.h5" for i in range(3)]
    dataset = SyntheticDataset(**READER)
    samples = read_samples(reference)
    cfg = teacher_config(label_cfg(reference))
    teacher = ICPFlow(cfg)
    for i in (0, 4):
        pair, got = dataset.pair(i), samples[i]
        np.testing.assert_array_equal(got["pc0"], pair.pc0)
        np.testing.assert_array_equal(got["pc1"], pair.pc1)
        np.testing.assert_array_equal(got["gt_flow"], pair.flow)
        np.testing.assert_array_equal(got["gt_classes"], pair.classes)
        np.testing.assert_array_equal(got["gt_dynamic"], pair.dynamic)
        assert got["sample_id"] == dataset.sample_id(i) and got["log_id"] == pair.log_id and got["dt"] == pair.dt
        result = teacher(pair.pc0, pair.pc1, pair.ego1_from_ego0, pair.ground0, pair.ground1)
        np.testing.assert_array_equal(got["flow"], result.flow)
        np.testing.assert_array_equal(got["confidence"], result.confidence)
        np.testing.assert_array_equal(got["cluster"], result.labels0)
        np.testing.assert_array_equal(got["ego1_from_ego0"], pair.ego1_from_ego0)
    with h5py.File(reference / "shard_000000.h5") as f:
        stored = yaml.safe_load(f.attrs["config"])
        assert stored["teacher"]["pairing"]["speed"] == cfg.pairing.speed and stored["shard_size"] == 2
        assert stored["dataset"]["reader"]["beams"] == 32 and stored["dataset"]["root"] is None
        assert f.attrs["config_hash"] == json.loads((reference / "index.json").read_text())["config_hash"]
    assert (reference / "failures.jsonl").read_text() == ""


def test_worker_count_does_not_change_output(reference, tmp_path, capsys):
    assert label(label_cfg(tmp_path, "workers=2"), progress=True) == 0
    assert_same(reference, tmp_path)
    out, err = capsys.readouterr()
    assert SUMMARY.fullmatch(out.strip()).groups() == ("5", "0", "0", str(tmp_path))
    final = err.split("\r")[-1].strip()  # the progress bar as it is left: rate in samples/s, elapsed<ETA
    assert re.fullmatch(r"labelling: 100%\|.*\| 5/5 \[\d\d:\d\d<00:00, +\d+\.\d\d samples/s\]", final), final
    assert "s/sample" not in err


def test_threads_per_worker_are_the_cores_divided_by_the_workers():
    import numba
    from threadpoolctl import threadpool_info

    before = numba.get_num_threads()
    with thread_limit(1):
        assert numba.get_num_threads() == 1
        assert all(pool["num_threads"] == 1 for pool in threadpool_info())
    assert numba.get_num_threads() == before
    assert available_cores() == len(os.sched_getaffinity(0))


def test_a_worker_runs_hdbscan_on_its_share_of_threads_without_changing_the_hash(tmp_path, monkeypatch):
    import icpflow.teacher

    built = []
    monkeypatch.setattr(icpflow.teacher, "ICPFlow", built.append)  # label_sample builds its teacher from this name
    teacher = teacher_config(label_cfg(tmp_path))
    assert teacher.clustering.n_jobs == 2
    job = LabelJob(SyntheticDataset(**READER), teacher, tmp_path, "teacher: {}\n")
    label_sample(job, 0, threads=1)  # the recorded "teacher" (None) then fails the sample: a failure record
    label_sample(job, 1, threads=8)
    assert [cfg.clustering.n_jobs for cfg in built] == [1, 2]  # never more than the config asks for
    assert built[0].replace(clustering={"n_jobs": 2}) == teacher and job.teacher_cfg == teacher
    write_shard_and_record(job, 0, [], [], [], 0, 0.0)
    with h5py.File(tmp_path / "shard_000000.h5") as f:
        assert f.attrs["config"] == "teacher: {}\n" and f.attrs["config_hash"] == job.hash


@pytest.mark.slow
def test_sigint_stops_cleanly_with_only_complete_shards(tmp_path):
    """A real SIGINT to label.py workers=1 (labelling in its main process, the teacher's threaded calls included: a
    stop inside scipy's threads once crashed it: icpflow.core.errors_and_signals.signals_held): exit 130, one line, the
    complete shards only, an index that says the run is not complete."""
    process = subprocess.Popen(
        label_script(tmp_path, "workers=1"),
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=default_sigint,
    )
    deadline = time.monotonic() + 120
    while not (tmp_path / "shard_000000.h5.json").exists() and process.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    assert 2 <= all_valid(tmp_path) < 5
    index = json.loads((tmp_path / "index.json").read_text())
    assert not index["complete"] and index["planned"] == 5 and 2 <= index["labelled"] < 5


#: label.py with the Ctrl-C landing where the pool spawns its first worker, in the main thread: after the worker process
#: started, before its channel was written (``multiprocessing``'s ``_launch``, as a probe of the start once landed)
STOP_WHILE_SPAWNING = """
import runpy, signal, sys


def in_launch(frame, event, arg):
    if frame.f_code.co_name != "spawnv_passfds" or frame.f_back.f_code.co_name != "_launch":
        return None

    def at_return(frame, event, arg):
        if event == "return":
            sys.settrace(None)
            signal.raise_signal(signal.SIGINT)
        return at_return

    return at_return


sys.settrace(in_launch)
sys.argv = sys.argv[1:]
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def test_a_stop_while_the_pool_spawns_a_worker_leaves_no_worker_traceback(tmp_path):
    """A Ctrl-C while the pool starts its worker (the main thread, between the worker's start and the write of its
    channel) waits until the worker has its channel: the run ends as any stopped run, one line and 130, and no worker
    prints ``EOFError: Ran out of input`` (the traceback once seen 1.6 s into a CI run's ``label.py``)."""
    script = label_script(tmp_path, "workers=2")
    done = subprocess.run(
        [sys.executable, "-c", STOP_WHILE_SPAWNING, *script[1:]],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=default_sigint,
    )
    assert done.returncode == 130, done.stderr
    assert "Traceback" not in done.stderr and "EOFError" not in done.stderr
    assert done.stderr.splitlines()[-1].startswith("label: interrupted; complete shards are kept in")


def test_other_config_is_refused_unless_overwrite(reference, tmp_path):
    out = tmp_path / "labels"
    shutil.copytree(reference, out)
    assert label(label_cfg(out, "icpflow.clustering.min_cluster_size=25"), progress=False) == 2
    assert (out / "config.yaml").read_text() == (reference / "config.yaml").read_text()
    assert (
        label(label_cfg(out, "icpflow.clustering.min_cluster_size=25", "overwrite=true", "limit=2"), progress=False)
        == 0
    )
    index = json.loads((out / "index.json").read_text())
    assert index["config_hash"] != json.loads((reference / "index.json").read_text())["config_hash"]
    assert [p.name for p in out.glob("shard_*.h5")] == ["shard_000000.h5"] and all_valid(out) == 2
    with h5py.File(out / "shard_000000.h5") as f:
        assert yaml.safe_load(f.attrs["config"])["teacher"]["clustering"]["min_cluster_size"] == 25


def test_refusal_message_is_one_line(reference, tmp_path):
    out = tmp_path / "labels"
    shutil.copytree(reference, out)
    run = subprocess.run(
        label_script(out, "icpflow.clustering.min_cluster_size=25"), cwd=tmp_path, capture_output=True, text=True
    )
    assert run.returncode == 2
    lines = [line for line in run.stderr.splitlines() if not line.startswith("label: dataset.teacher keys")]
    assert len(lines) == 1 and "labelled with another config" in lines[0] and "overwrite=true" in lines[0]
    assert "teacher.clustering.min_cluster_size: 30 -> 25" in lines[0]


def test_truncated_and_corrupt_shards_are_redone(reference, tmp_path, capsys):
    out = tmp_path / "labels"
    shutil.copytree(reference, out)
    truncated = out / "shard_000001.h5"
    truncated.write_bytes(truncated.read_bytes()[:5000])
    corrupt = out / "shard_000002.h5"
    with h5py.File(corrupt) as f:
        offset = f["samples/00000/flow"].id.get_chunk_info(0).byte_offset
    data = bytearray(corrupt.read_bytes())
    data[offset + 100] ^= 0x5A
    corrupt.write_bytes(bytes(data))
    assert label(label_cfg(out), progress=False) == 0
    assert "3 samples labelled, 2 skipped" in capsys.readouterr().out
    assert all_valid(out) == 5
    assert_same(reference, out)


def test_failures_are_recorded_and_the_run_goes_on(tmp_path, capsys):
    cfg = label_cfg(tmp_path, "dataset.reader._target_=helpers.readers.FlakySynthetic")
    status = label(cfg, progress=False)
    assert status == 1
    n0 = len(SyntheticDataset(**READER).pair(3).pc0)
    failures = [json.loads(line) for line in (tmp_path / "failures.jsonl").read_text().splitlines()]
    assert failures[0] == {
        "index": 1,
        "sample_id": "synthetic-train-0-32b/000001+1",
        "file": "/data/log/000001.bin",
        "reason": "FramePairError: /data/log/000001.bin: pc0 must have shape (N, 3), got (7,)",
    }
    assert failures[1] == {
        "index": 3,
        "sample_id": "synthetic-train-0-32b/000003+1",
        "file": "synthetic-train-0-32b/000003+1",
        "reason": f"ValueError: ICPFlow: ground0 must have shape (0,), got ({n0},)",
    }
    assert len(failures) == 2
    index = json.loads((tmp_path / "index.json").read_text())
    labelled = [s["index"] for shard in index["shards"] for s in shard["samples"]]
    assert sorted(labelled + [f["index"] for f in failures]) == [0, 1, 2, 3, 4]
    out = capsys.readouterr()
    assert SUMMARY.fullmatch(out.out.strip()).groups() == ("3", "0", "2", str(tmp_path))
    assert "failed synthetic-train-0-32b/000001+1" in out.err
    assert all_valid(tmp_path) == 3
    before = {p.name: p.stat().st_mtime_ns for p in tmp_path.glob("shard_*.h5")}
    assert label(cfg, progress=False) == 1  # a rerun tries the failed samples again, they fail again
    assert SUMMARY.fullmatch(capsys.readouterr().out.strip()).groups() == ("0", "3", "2", str(tmp_path))
    assert [json.loads(line) for line in (tmp_path / "failures.jsonl").read_text().splitlines()] == failures
    after = {p.name: p.stat().st_mtime_ns for p in tmp_path.glob("shard_*.h5")}
    assert after["shard_000002.h5"] == before["shard_000002.h5"]  # no failure there: not rewritten
    assert after["shard_000000.h5"] != before["shard_000000.h5"] and all_valid(tmp_path) == 3


def test_shard_split_jobs_add_up_to_the_whole(reference, tmp_path, caplog, capsys):
    """The union of the jobs is the whole; the index says how complete the folder is after each (issue 45: a
    stopped or partial labelling was trained on without a word), and train.py and eval.py say it."""
    from fastflow3d.training.trainer import check_data
    from icpflow.evaluation.methods import ShardMethod

    assert label(label_cfg(tmp_path, "shard_index=1", "num_shards=2"), progress=False) == 0
    assert sorted(p.name for p in tmp_path.glob("shard_*.h5")) == ["shard_000001.h5"]
    index = json.loads((tmp_path / "index.json").read_text())
    assert (index["complete"], index["labelled"], index["failed"], index["planned"]) == (False, 2, 0, 5)
    said = f"{tmp_path}: label.py did not finish this folder: 2 of 5 samples labelled; rerun the label.py command"
    assert ShardDataset(tmp_path).incomplete().startswith(said)
    with caplog.at_level(logging.WARNING, logger="fastflow3d.training"):
        data = {"train": str(tmp_path), "val": str(reference)}
        check_data(OmegaConf.create({"data": data, "loss": {"name": "x"}, "out_dir": str(tmp_path / "run")}))
    assert [r.getMessage() for r in caplog.records if "did not finish" in r.getMessage()][0].startswith(
        f"data.train: {said}"
    )
    ShardMethod(tmp_path)
    assert f"eval: warning: shards={said}" in capsys.readouterr().err
    assert label(label_cfg(tmp_path, "shard_index=0", "num_shards=2"), progress=False) == 0
    assert_same(reference, tmp_path)
    index = json.loads((tmp_path / "index.json").read_text())
    assert (index["complete"], index["labelled"], index["planned"]) == (True, 5, 5)
    assert ShardDataset(tmp_path).incomplete() is None


@pytest.mark.slow
def test_ray_runner_matches_local(reference, tmp_path):
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install icpflow[test])")
    try:
        assert label(label_cfg(tmp_path, "runner=ray", "workers=2"), progress=False) == 0
        assert ray.cluster_resources().get("CPU") == 2
    finally:
        ray.shutdown()
    assert_same(reference, tmp_path)


@pytest.mark.parametrize("root", ["missing", "empty", None])
def test_missing_or_empty_root_is_one_line(tmp_path, root):
    args = ["dataset=kitti"]
    if root == "missing":
        args.append(f"dataset.root={tmp_path / 'nowhere'}")
    elif root == "empty":
        (tmp_path / "empty").mkdir()
        args.append(f"dataset.root={tmp_path / 'empty'}")
    run = subprocess.run(
        [sys.executable, str(REPO / "label.py"), *args, f"out_dir={tmp_path / 'out'}"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert run.returncode == 2
    assert len(run.stderr.strip().splitlines()) == 1 and "Traceback" not in run.stderr
    expected = {"missing": "does not exist", "empty": "is empty", None: "dataset.root is not set"}[root]
    assert run.stderr.startswith("label: dataset kitti: ") and expected in run.stderr
    assert not (tmp_path / "out").exists()


def _sweep_times(points):
    """Capture time of each point of a spinning LiDAR (one turn in 0.1 s, starting behind the sensor)."""
    return ((np.arctan2(points[:, 1], points[:, 0]) + np.pi) / (2 * np.pi) * 0.1).astype(np.float32)


class TimedSynthetic(SyntheticDataset):
    """The small synthetic world with per-point capture times, so the teacher's de-skew step has work."""

    def pair(self, index, horizon=1):
        pair = super().pair(index, horizon)
        return pair.replace(time0=_sweep_times(pair.pc0), time1=_sweep_times(pair.pc1))


def test_long_horizon_direct_and_tracker_pass_point_times(tmp_path):
    dataset = TimedSynthetic(**READER, max_horizon=2)
    common = [
        f"dataset.reader._target_={__name__}.TimedSynthetic",
        "dataset.reader.max_horizon=2",
        "horizon=2",
        "limit=2",
        "icpflow.deskew.enabled=true",
    ]
    cfg = teacher_config(label_cfg(tmp_path, *common))
    assert cfg.deskew.enabled
    direct_out, tracked_out = tmp_path / "direct", tmp_path / "tracker"
    assert label(label_cfg(direct_out, *common), progress=False) == 0
    assert label(label_cfg(tracked_out, *common, "tracker=true"), progress=False) == 0
    pair = dataset.pair(1, horizon=2)
    direct, tracked = read_samples(direct_out)[1], read_samples(tracked_out)[1]
    assert direct["sample_id"] == tracked["sample_id"] == pair.sample_id == "synthetic-train-0-32b/000001+2"
    expected = ICPFlow(cfg)(
        pair.pc0, pair.pc1, pair.ego1_from_ego0, pair.ground0, pair.ground1, pair.time0, pair.time1, gap=2, dt=pair.dt
    )
    assert expected.n_deskewed > 0
    np.testing.assert_array_equal(direct["pc1"], pair.pc1)
    np.testing.assert_array_equal(direct["flow"], expected.flow)
    np.testing.assert_array_equal(direct["gt_flow"], pair.flow)
    np.testing.assert_array_equal(tracked["pc1"], pair.pc1)
    np.testing.assert_allclose(tracked["ego1_from_ego0"], pair.ego1_from_ego0, atol=1e-9)
    assert (tracked["cluster"] == -1).all()
    step = dataset.pair(1, horizon=1)
    scans = [pair.pc0, step.pc1, pair.pc1]
    egos = [step.ego1_from_ego0, pair.ego1_from_ego0 @ np.linalg.inv(step.ego1_from_ego0)]
    grounds = [pair.ground0, step.ground1, pair.ground1]
    chained = long_horizon_flow(
        ICPFlow(cfg),
        scans,
        egos,
        grounds,
        mode="tracker",
        times=[pair.time0, step.time1, pair.time1],
        dts=[step.dt, pair.dt - step.dt],
    )
    np.testing.assert_array_equal(tracked["flow"], chained.flow)
    np.testing.assert_array_equal(tracked["confidence"], chained.confidence)
    assert chained.chained.any() and not np.array_equal(tracked["flow"], direct["flow"])
    timeless = long_horizon_flow(ICPFlow(cfg), scans, egos, grounds, mode="tracker")
    assert not np.array_equal(timeless.flow, chained.flow)  # the times reach the teacher and matter


@pytest.mark.parametrize(
    "horizon, override, message",
    [
        (
            5,
            "dataset.reader.max_horizon=5",
            "horizon=5 exceeds the teacher's max_frame_gap 4 (icpflow.pairing.max_frame_gap=...)",
        ),
        (
            2,
            "dataset.reader.frames_per_sequence=2",
            "dataset synthetic: synthetic: max_horizon must lie in 1..1 for 2 "
            "frames per sequence, got 2 (with dataset.reader.max_horizon=2)",
        ),
    ],
)
def test_horizon_beyond_teacher_or_dataset_is_refused(tmp_path, capsys, horizon, override, message):
    cfg = label_cfg(tmp_path / "out", f"horizon={horizon}", override)
    assert label(cfg, progress=False) == 2
    assert capsys.readouterr().err == f"label: {message}\n"
    assert not (tmp_path / "out").exists()


def test_failure_ids_name_the_pair_of_the_horizon(tmp_path):
    cfg = label_cfg(
        tmp_path, "dataset.reader._target_=helpers.readers.FlakySynthetic", "dataset.reader.max_horizon=2", "horizon=2"
    )
    assert label(cfg, progress=False) == 1
    failures = [json.loads(line) for line in (tmp_path / "failures.jsonl").read_text().splitlines()]
    # sample 1 fails in the reader (no pair: the reader's id of the sample), sample 3 in the teacher (the pair's id)
    assert [(f["index"], f["sample_id"]) for f in failures] == [
        (1, "synthetic-train-0-32b/000001+1"),
        (3, "synthetic-train-0-32b/000003+2"),
    ]
    index = json.loads((tmp_path / "index.json").read_text())
    assert [s["sample_id"] for shard in index["shards"] for s in shard["samples"]] == [
        "synthetic-train-0-32b/000000+2",
        "synthetic-train-0-32b/000002+2",
    ]


def _write_pairs(root: Path, names: list[str], seeds: list[int]) -> None:
    """``<root>/<name>.npz`` pairs (the pairs dataset) made from samples ``seeds`` of the small synthetic world."""
    dataset = SyntheticDataset(**READER)
    root.mkdir(parents=True, exist_ok=True)
    for name, seed in zip(names, seeds, strict=True):
        pair = dataset.pair(seed)
        np.savez(
            root / f"{name}.npz",
            pc0=pair.pc0,
            pc1=pair.pc1,
            ego1_from_ego0=pair.ego1_from_ego0,
            ground0=pair.ground0,
            ground1=pair.ground1,
        )


def _pairs_cfg(out_dir, root, *overrides):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose(
            "label", ["dataset=pairs", f"dataset.root={root}", f"out_dir={out_dir}", "workers=1", *overrides]
        )


def test_another_root_into_the_same_out_dir_is_refused(tmp_path, capsys):
    _write_pairs(tmp_path / "a", ["000000"], [0])
    _write_pairs(tmp_path / "b", ["000000"], [1])  # same names, other data
    out = tmp_path / "out"
    assert label(_pairs_cfg(out, tmp_path / "a"), progress=False) == 0
    capsys.readouterr()
    assert label(_pairs_cfg(out, tmp_path / "b"), progress=False) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "labelled with another config" in err
    assert f"dataset.root: {tmp_path / 'a'} -> {tmp_path / 'b'}" in err
    with h5py.File(out / "shard_000000.h5") as f:
        assert yaml.safe_load(f.attrs["config"])["dataset"]["root"] == str(tmp_path / "a")


def test_resume_redoes_shards_whose_samples_changed(tmp_path, capsys):
    root, out = tmp_path / "pairs", tmp_path / "out"
    _write_pairs(root, ["a", "c", "d"], [0, 1, 2])
    assert label(_pairs_cfg(out, root, "shard_size=1"), progress=False) == 0
    _write_pairs(root, ["b"], [3])  # sorts between a and c: the samples after it move up one index
    capsys.readouterr()
    assert label(_pairs_cfg(out, root, "shard_size=1"), progress=False) == 0
    assert SUMMARY.fullmatch(capsys.readouterr().out.strip()).groups() == ("3", "1", "0", str(out))
    assert ShardDataset(out).sample_ids == ["a", "b", "c", "d"]
    stored, fresh = read_samples(out), [SyntheticDataset(**READER).pair(seed) for seed in (0, 3, 1, 2)]
    for got, pair in zip(stored, fresh, strict=True):
        np.testing.assert_array_equal(got["pc0"], pair.pc0)


@pytest.mark.parametrize(
    "option, words",
    [
        ("runner=ray", "runner=ray needs the ray package"),
        ("compression=zstd", "compression must be one of none, gzip, lzf"),
        ("runner=spark", "runner must be one of local, ray"),
        ("workers=0", "workers must be an integer >= 1"),
        ("icpflow.clustering.min_cluster_size=0", "icpflow.clustering.min_cluster_size must be an integer >= 1"),
    ],
)
def test_bad_options_are_one_line(tmp_path, capsys, monkeypatch, option, words):
    """A value its schema's rule refuses (or a runner whose package is missing): one line naming the option and
    what it takes, before any work (no out_dir)."""
    monkeypatch.setitem(sys.modules, "ray", None)  # as if ray were not installed
    assert label(label_cfg(tmp_path / "out", option), progress=False) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"label: {words}") and option.split("=")[1] in line
    assert not (tmp_path / "out").exists()


def test_gzip_compression_through_label_py(reference, tmp_path):
    run = subprocess.run(
        label_script(tmp_path, "compression=gzip", "workers=1"), cwd=tmp_path, capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr
    assert_same(reference, tmp_path)
    with h5py.File(tmp_path / "shard_000000.h5") as f, h5py.File(reference / "shard_000000.h5") as g:
        assert f["samples/00000/flow"].compression == "gzip" and g["samples/00000/flow"].compression is None
        assert f.attrs["config_hash"] == g.attrs["config_hash"]  # compression does not change the labels


@pytest.mark.slow
def test_ctrl_c_to_the_process_group_with_two_workers(reference, tmp_path):
    """Ctrl-C (SIGINT to the process group: the main process and its workers) once the first shard is written: exit
    130, no Traceback, no process left, the complete shards only; the rerun labels the rest and matches the
    uninterrupted run. (SIGTERM and SIGKILL to the main process only, the rerun after them:
    tests/project/test_faults.py.)"""
    args = ["dataset.reader._target_=helpers.labelling.SlowSynthetic", "workers=2"]
    process = subprocess.Popen(
        label_script(tmp_path, *args),
        cwd=tmp_path,
        env=TESTS_ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=default_sigint,
    )
    deadline = time.monotonic() + 120
    while not (tmp_path / "shard_000000.h5.json").exists() and process.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    os.killpg(process.pid, signal.SIGINT)  # what a terminal's Ctrl-C does: the main process and its workers
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    deadline = time.monotonic() + 15  # workers being torn down may take a moment under load
    while running_in_group(process.pid) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert running_in_group(process.pid) == []  # no worker outlives the run
    assert all_valid(tmp_path) == 2 and sorted(p.name for p in tmp_path.glob("shard_*")) == [
        "shard_000000.h5",
        "shard_000000.h5.json",
    ]
    run = subprocess.run(label_script(tmp_path, *args), cwd=tmp_path, env=RERUN_ENV, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert SUMMARY.search(run.stdout).groups()[:3] == ("3", "2", "0")
    assert_same(reference, tmp_path)


class KillingSynthetic(SyntheticDataset):
    """The small synthetic world whose reader kills its worker process on sample 3 (as a crash in native code or
    the out-of-memory killer would), and which names the number of threads a worker runs on in ``log_id``."""

    def pair(self, index, horizon=1):
        import numba

        if index == 3 and multiprocessing.parent_process() is not None:
            os.kill(os.getpid(), signal.SIGKILL)
        return super().pair(index, horizon).replace(log_id=f"threads {numba.get_num_threads()}")


def test_a_worker_that_dies_fails_its_sample_only(reference, tmp_path, capsys):
    cfg = label_cfg(tmp_path, f"dataset.reader._target_={__name__}.KillingSynthetic", "workers=2")
    assert label(cfg, progress=False) == 1
    out, err = capsys.readouterr()
    assert SUMMARY.fullmatch(out.strip()).groups() == ("4", "0", "1", str(tmp_path))
    assert "Traceback" not in err and "failed synthetic-train-0-32b/000003+1" in err
    failures = [json.loads(line) for line in (tmp_path / "failures.jsonl").read_text().splitlines()]
    assert failures == [
        {
            "index": 3,
            "sample_id": "synthetic-train-0-32b/000003+1",
            "file": "synthetic-train-0-32b/000003+1",
            "reason": DIED,
            "deaths": 1,
        }
    ]
    got, expected = read_samples(tmp_path), read_samples(reference)
    assert [s["sample_id"] for s in got] == [expected[i]["sample_id"] for i in (0, 1, 2, 4)]
    threads = f"threads {max(1, available_cores() // 2)}"
    for sample, want in zip(got, [expected[i] for i in (0, 1, 2, 4)], strict=True):
        assert sample.pop("log_id") == threads and want.pop("log_id") == "synthetic-train-0-32b"
        for key in want:
            np.testing.assert_array_equal(sample[key], want[key], err_msg=key)
    assert label(cfg, progress=False) == 1  # the rerun tries sample 3 again: it kills its worker a second time
    assert SUMMARY.fullmatch(capsys.readouterr().out.strip()).groups() == ("0", "4", "1", str(tmp_path))
    failures = [json.loads(line) for line in (tmp_path / "failures.jsonl").read_text().splitlines()]
    assert failures[0]["deaths"] == 2 and "2 times in a row, not tried again" in failures[0]["reason"]
    records = {p.name: p.stat().st_mtime_ns for p in tmp_path.glob("shard_*.json")}
    assert label(cfg, progress=False) == 1  # then it is recorded and skipped, not retried forever
    assert SUMMARY.fullmatch(capsys.readouterr().out.strip()).groups() == ("0", "4", "1", str(tmp_path))
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.glob("shard_*.json")} == records


@pytest.mark.slow
def test_multirun_jobs_label_the_union(reference, tmp_path):
    flaky = (
        "dataset.reader._target_=helpers.readers.FlakySynthetic"  # samples 1 and 3 fail: each job ends with status 1
    )
    command = label_script(tmp_path / "labels", flaky, "workers=1", "shard_index=0,1", "num_shards=2")
    run = subprocess.run(
        [*command[:2], "-m", *command[2:]], cwd=tmp_path, env=TESTS_ENV, capture_output=True, text=True
    )
    assert run.returncode == 0, run.stderr
    assert [m.group(1, 2, 3) for m in SUMMARY.finditer(run.stdout)] == [("2", "0", "1"), ("1", "0", "1")]
    index = json.loads((tmp_path / "labels" / "index.json").read_text())
    assert [shard["file"] for shard in index["shards"]] == [f"shard_00000{i}.h5" for i in range(3)]
    failures = (tmp_path / "labels" / "failures.jsonl").read_text().splitlines()
    assert [json.loads(line)["index"] for line in failures] == [1, 3]
    got, expected = read_samples(tmp_path / "labels"), read_samples(reference)
    for sample, want in zip(got, [expected[i] for i in (0, 2, 4)], strict=True):
        for key in want:
            np.testing.assert_array_equal(sample[key], want[key], err_msg=key)


class InterruptedInKernel(SyntheticDataset):
    """Reading a pair raises what Ctrl-C inside a numba kernel gives: a SystemError over the KeyboardInterrupt."""

    def pair(self, index, horizon=1):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as stop:
            raise SystemError("CPUDispatcher(...) returned a result with an exception set") from stop


class BrokenInKernel(SyntheticDataset):
    """Reading a pair raises a SystemError over an ordinary error (a failing sample, not an interrupt)."""

    def pair(self, index, horizon=1):
        try:
            raise ValueError("bad values")
        except ValueError as cause:
            raise SystemError("CPUDispatcher(...) returned a result with an exception set") from cause


def test_an_interrupt_inside_a_kernel_stops_the_run_and_fails_no_sample(tmp_path):
    job = LabelJob(InterruptedInKernel(**READER), teacher_config(label_cfg(tmp_path)), tmp_path, "teacher: {}\n")
    with pytest.raises(KeyboardInterrupt):
        label_sample(job, 0, threads=1)
    broken = LabelJob(BrokenInKernel(**READER), job.teacher_cfg, tmp_path, "teacher: {}\n")
    assert label_sample(broken, 0, threads=1)["failure"]["reason"].startswith("SystemError")  # this sample only
