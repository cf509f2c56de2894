"""The labelling stage end to end: the real teacher on a small synthetic world (32 beams, 2 deg azimuth)."""

import json
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

from icpflow.datasets.synthetic import SyntheticDataset
from icpflow.frames import FramePairError
from icpflow.labelling.cli import label, teacher_config
from icpflow.shards import ShardDataset, verify_shard
from icpflow.teacher import ICPFlow
from icpflow.teacher.tracker import long_horizon_flow

REPO = Path(__file__).resolve().parents[1]
SMALL = ["dataset.reader.beams=32", "dataset.reader.azimuth_resolution_deg=2.0", "dataset.reader.num_sequences=1",
         "dataset.reader.frames_per_sequence=6", "shard_size=2", "limit=5"]
READER = {"split": "train", "num_sequences": 1, "frames_per_sequence": 6, "beams": 32, "azimuth_resolution_deg": 2.0}


def _cfg(out_dir, *overrides):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose("label", [*SMALL, f"out_dir={out_dir}", "workers=1", *overrides])


def _samples(out_dir) -> list[dict]:
    dataset = ShardDataset(out_dir)
    samples = [dataset[i] for i in range(len(dataset))]
    dataset.close()
    return samples


def _assert_same(out_a, out_b):
    a, b = _samples(out_a), _samples(out_b)
    assert [s["sample_id"] for s in a] == [s["sample_id"] for s in b]
    for x, y in zip(a, b, strict=True):
        assert set(x) == set(y)
        for key in x:
            np.testing.assert_array_equal(x[key], y[key], err_msg=key)


def _all_valid(out_dir) -> int:
    index = json.loads((Path(out_dir) / "index.json").read_text())
    for shard in index["shards"]:
        verify_shard(Path(out_dir) / shard["file"], index["config_hash"], len(shard["samples"]))
    assert not list(Path(out_dir).glob("shard_*.tmp-*"))
    return sum(len(shard["samples"]) for shard in index["shards"])


def _script(out_dir, *overrides):
    return [sys.executable, str(REPO / "label.py"), *SMALL, f"out_dir={out_dir}", *overrides]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted single-worker run: 5 samples in shards of 2, 2, 1."""
    out = tmp_path_factory.mktemp("reference") / "labels"
    assert label(_cfg(out), progress=False) == 0
    return out


def test_round_trip_holds_reader_input_and_teacher_output(reference):
    assert _all_valid(reference) == 5
    assert sorted(p.name for p in reference.glob("shard_*.h5")) == [f"shard_00000{i}.h5" for i in range(3)]
    dataset = SyntheticDataset(**READER)
    samples = _samples(reference)
    cfg = teacher_config(_cfg(reference))
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
        assert stored["teacher"]["speed"] == cfg.speed and stored["shard_size"] == 2
        assert stored["dataset"]["reader"]["beams"] == 32
        assert f.attrs["config_hash"] == json.loads((reference / "index.json").read_text())["config_hash"]
    assert (reference / "failures.jsonl").read_text() == ""


def test_worker_count_does_not_change_output(reference, tmp_path):
    assert label(_cfg(tmp_path, "workers=2"), progress=False) == 0
    _assert_same(reference, tmp_path)


def test_resume_after_sigkill_matches_uninterrupted_run(reference, tmp_path):
    process = subprocess.Popen(_script(tmp_path, "workers=1"), cwd=tmp_path, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not (tmp_path / "shard_000000.h5.json").exists() and process.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert process.returncode == -signal.SIGKILL
    for shard in tmp_path.glob("shard_*.h5"):  # whatever is there under a final name is complete
        verify_shard(shard)
    run = subprocess.run(_script(tmp_path, "workers=1"), cwd=tmp_path, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    done, skipped = map(int, re.search(r"(\d+) samples labelled, (\d+) skipped", run.stdout).groups())
    assert skipped >= 2 and done + skipped == 5
    assert _all_valid(tmp_path) == 5
    _assert_same(reference, tmp_path)


def test_sigint_stops_cleanly_with_only_complete_shards(tmp_path):
    process = subprocess.Popen(_script(tmp_path, "workers=1"), cwd=tmp_path, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (tmp_path / "shard_000000.h5.json").exists() and process.poll() is None:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=60)
    assert process.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err
    assert 2 <= _all_valid(tmp_path) < 5


def test_other_config_is_refused_unless_overwrite(reference, tmp_path):
    out = tmp_path / "labels"
    shutil.copytree(reference, out)
    assert label(_cfg(out, "icpflow.min_cluster_size=25"), progress=False) == 2
    assert (out / "config.yaml").read_text() == (reference / "config.yaml").read_text()
    assert label(_cfg(out, "icpflow.min_cluster_size=25", "overwrite=true", "limit=2"), progress=False) == 0
    index = json.loads((out / "index.json").read_text())
    assert index["config_hash"] != json.loads((reference / "index.json").read_text())["config_hash"]
    assert [p.name for p in out.glob("shard_*.h5")] == ["shard_000000.h5"] and _all_valid(out) == 2
    with h5py.File(out / "shard_000000.h5") as f:
        assert yaml.safe_load(f.attrs["config"])["teacher"]["min_cluster_size"] == 25


def test_refusal_message_is_one_line(reference, tmp_path):
    out = tmp_path / "labels"
    shutil.copytree(reference, out)
    run = subprocess.run(_script(out, "icpflow.min_cluster_size=25"), cwd=tmp_path, capture_output=True, text=True)
    assert run.returncode == 2
    lines = [line for line in run.stderr.splitlines() if not line.startswith("label: dataset.teacher keys")]
    assert len(lines) == 1 and "labelled with another config" in lines[0] and "overwrite=true" in lines[0]


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
    assert label(_cfg(out), progress=False) == 0
    assert "3 samples labelled, 2 skipped" in capsys.readouterr().out
    assert _all_valid(out) == 5
    _assert_same(reference, out)


class FlakySynthetic(SyntheticDataset):
    """The small synthetic world where the reader fails on sample 1 and sample 3 reaches the teacher with an empty
    pc0 but a full ground mask (the teacher rejects it)."""

    def pair(self, index, horizon=1):
        if index == 1:
            raise FramePairError("/data/log/000001.bin: pc0 must have shape (N, 3), got (7,)")
        pair = super().pair(index, horizon)
        if index == 3:
            pair.pc0 = pair.pc0[:0]
        return pair


def test_failures_are_recorded_and_the_run_goes_on(tmp_path, capsys):
    cfg = _cfg(tmp_path, f"dataset.reader._target_={__name__}.FlakySynthetic")
    status = label(cfg, progress=False)
    assert status == 1
    n0 = len(SyntheticDataset(**READER).pair(3).pc0)
    failures = [json.loads(line) for line in (tmp_path / "failures.jsonl").read_text().splitlines()]
    assert failures[0] == {"index": 1, "sample_id": "synthetic-train-0-32b/000001+1", "file": "/data/log/000001.bin",
                           "reason": "FramePairError: /data/log/000001.bin: pc0 must have shape (N, 3), got (7,)"}
    assert failures[1] == {"index": 3, "sample_id": "synthetic-train-0-32b/000003+1",
                           "file": "synthetic-train-0-32b/000003+1",
                           "reason": f"ValueError: ICPFlow: ground0 must have shape (0,), got ({n0},)"}
    assert len(failures) == 2
    index = json.loads((tmp_path / "index.json").read_text())
    labelled = [s["index"] for shard in index["shards"] for s in shard["samples"]]
    assert sorted(labelled + [f["index"] for f in failures]) == [0, 1, 2, 3, 4]
    out = capsys.readouterr()
    assert "3 samples labelled, 0 skipped (already done), 2 failed" in out.out and "failed synthetic-train-0-32b/000001+1" in out.err
    assert _all_valid(tmp_path) == 3
    assert label(cfg, progress=False) == 1  # a rerun keeps the record and skips everything
    assert "0 samples labelled" in capsys.readouterr().out


def test_shard_split_jobs_add_up_to_the_whole(reference, tmp_path):
    assert label(_cfg(tmp_path, "shard_index=1", "num_shards=2"), progress=False) == 0
    assert sorted(p.name for p in tmp_path.glob("shard_*.h5")) == ["shard_000001.h5"]
    assert label(_cfg(tmp_path, "shard_index=0", "num_shards=2"), progress=False) == 0
    _assert_same(reference, tmp_path)


def test_ray_runner_matches_local(reference, tmp_path):
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install icpflow[test])")
    try:
        assert label(_cfg(tmp_path, "runner=ray", "workers=2"), progress=False) == 0
        assert ray.cluster_resources().get("CPU") == 2
    finally:
        ray.shutdown()
    _assert_same(reference, tmp_path)


@pytest.mark.parametrize("root", ["missing", "empty", None])
def test_missing_or_empty_root_is_one_line(tmp_path, root):
    args = ["dataset=kitti"]
    if root == "missing":
        args.append(f"dataset.root={tmp_path / 'nowhere'}")
    elif root == "empty":
        (tmp_path / "empty").mkdir()
        args.append(f"dataset.root={tmp_path / 'empty'}")
    run = subprocess.run([sys.executable, str(REPO / "label.py"), *args, f"out_dir={tmp_path / 'out'}"],
                         cwd=tmp_path, capture_output=True, text=True)
    assert run.returncode == 2
    assert len(run.stderr.strip().splitlines()) == 1 and "Traceback" not in run.stderr
    expected = {"missing": "does not exist", "empty": "is empty", None: "dataset.root is not set"}[root]
    assert run.stderr.startswith("label: dataset kitti: ") and expected in run.stderr
    assert not (tmp_path / "out").exists()


def test_long_horizon_direct_and_tracker(tmp_path):
    dataset = SyntheticDataset(**READER)
    cfg = teacher_config(_cfg(tmp_path))
    direct_out, tracked_out = tmp_path / "direct", tmp_path / "tracker"
    assert label(_cfg(direct_out, "horizon=2", "limit=2"), progress=False) == 0
    assert label(_cfg(tracked_out, "horizon=2", "tracker=true", "limit=2"), progress=False) == 0
    pair = dataset.pair(1, horizon=2)
    direct, tracked = _samples(direct_out)[1], _samples(tracked_out)[1]
    expected = ICPFlow(cfg)(pair.pc0, pair.pc1, pair.ego1_from_ego0, pair.ground0, pair.ground1, gap=2)
    np.testing.assert_array_equal(direct["pc1"], pair.pc1)
    np.testing.assert_array_equal(direct["flow"], expected.flow)
    np.testing.assert_array_equal(direct["gt_flow"], pair.flow)
    np.testing.assert_array_equal(tracked["pc1"], pair.pc1)
    np.testing.assert_allclose(tracked["ego1_from_ego0"], pair.ego1_from_ego0, atol=1e-9)
    assert (tracked["cluster"] == -1).all()
    steps = [dataset.pair(1, horizon=1), pair]
    egos = [steps[0].ego1_from_ego0, pair.ego1_from_ego0 @ np.linalg.inv(steps[0].ego1_from_ego0)]
    chained = long_horizon_flow(ICPFlow(cfg), [pair.pc0, steps[0].pc1, pair.pc1], egos,
                                [pair.ground0, steps[0].ground1, pair.ground1], mode="tracker")
    np.testing.assert_array_equal(tracked["flow"], chained.flow)
    np.testing.assert_array_equal(tracked["confidence"], chained.confidence)
    assert chained.chained.any() and not np.array_equal(tracked["flow"], direct["flow"])
