"""Shard schema, atomic writer, reader and verification on hand-made samples."""

import json
import pickle

import h5py
import numpy as np
import pytest
import torch

import icpflow
from icpflow.labelling.plan import plan_shards
from icpflow.shards import SCHEMA_VERSION, ShardDataset, ShardError, verify_shard, write_shard
from icpflow.shards.schema import COMPRESSIONS, group_name

from helpers.shards import write_labels


def _sample(seed: int, n0: int, n1: int, gt: bool) -> dict:
    rng = np.random.default_rng(seed)
    sample = {
        "pc0": rng.normal(size=(n0, 3)).astype(np.float32),
        "pc1": rng.normal(size=(n1, 3)).astype(np.float32),
        "ground0": rng.random(n0) < 0.5,
        "ground1": rng.random(n1) < 0.5,
        "ego1_from_ego0": np.array([[1, 0, 0, -1.5], [0, 1, 0, 0.25], [0, 0, 1, 0], [0, 0, 0, 1]], np.float64),
        "flow": rng.normal(size=(n0, 3)).astype(np.float32),
        "confidence": rng.random(n0).astype(np.float32),
        "cluster": rng.integers(-1, 5, n0).astype(np.int32),
        "attrs": {
            "sample_id": f"log/{seed:06d}",
            "log_id": "log",
            "index": seed,
            "timestamp0_ns": 1000 * seed,
            "timestamp1_ns": 1000 * seed + 100,
            "dt": 0.1,
        },
    }
    if gt:
        sample.update(
            gt_flow=rng.normal(size=(n0, 3)).astype(np.float32),
            gt_flow_valid=np.ones(n0, bool),
            gt_classes=rng.integers(0, 3, n0).astype(np.int32),
            gt_dynamic=rng.random(n0) < 0.2,
        )
    return sample


@pytest.fixture
def written(tmp_path):
    """Two shards (3 + 1 samples, the second without ground truth) and their index."""
    shards = {
        "shard_000000.h5": [_sample(i, 50 + i, 40 + i, True) for i in range(3)],
        "shard_000001.h5": [_sample(3, 7, 9, False)],
    }
    write_labels(tmp_path, shards, "teacher: {speed: 1.0}\n", "abc123", "gzip")
    return tmp_path, [s for samples in shards.values() for s in samples]


def test_round_trip_exact(written):
    root, samples = written
    dataset = ShardDataset(root)
    assert len(dataset) == 4
    for i, expected in enumerate(samples):
        got = dataset[i]
        arrays = {k: v for k, v in expected.items() if k != "attrs"}
        assert set(got) == set(arrays) | {"sample_id", "log_id", "dt"}
        for key, value in arrays.items():
            assert got[key].dtype == value.dtype, key
            np.testing.assert_array_equal(got[key], value, err_msg=key)
        assert got["sample_id"] == expected["attrs"]["sample_id"] and got["log_id"] == "log" and got["dt"] == 0.1
    with pytest.raises(IndexError):
        dataset[4]
    with h5py.File(root / "shard_000000.h5") as f:
        assert f.attrs["config"] == "teacher: {speed: 1.0}\n" and f.attrs["config_hash"] == "abc123"
        assert f.attrs["package_version"] == icpflow.__version__ and f.attrs["schema_version"] == SCHEMA_VERSION
        assert f[group_name(2)].attrs["timestamp1_ns"] == 2100
        assert f[group_name(0)]["pc0"].compression == "gzip"
    assert not list(root.glob("*.tmp-*"))


def test_reader_pickles_and_works_in_dataloader_workers(written):
    root, samples = written
    dataset = ShardDataset(root)
    dataset[0]  # opens a file in this process; the copy must not carry the handle
    clone = pickle.loads(pickle.dumps(dataset))
    assert clone._files == {}
    loader = torch.utils.data.DataLoader(dataset, batch_size=None, num_workers=2)
    got = [item["pc0"].numpy() for item in loader]
    for value, expected in zip(got, samples, strict=True):
        np.testing.assert_array_equal(value, expected["pc0"])


def test_verify_accepts_complete_and_checks_hash_and_count(written):
    root, _ = written
    assert verify_shard(root / "shard_000000.h5", "abc123", 3) == 3
    with pytest.raises(ShardError, match="made by config abc123, expected zzz"):
        verify_shard(root / "shard_000000.h5", "zzz")
    with pytest.raises(ShardError, match="holds 3 samples, expected 4"):
        verify_shard(root / "shard_000000.h5", num_samples=4)
    with pytest.raises(ShardError, match="missing"):
        verify_shard(root / "shard_000009.h5")


def test_verify_detects_truncation(written):
    root, _ = written
    path = root / "shard_000000.h5"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ShardError, match="shard_000000.h5: unreadable"):
        verify_shard(path)


def test_verify_detects_flipped_bytes_in_data(written):
    root, samples = written
    path = root / "shard_000000.h5"
    with h5py.File(path) as f:
        offset = f[group_name(1)]["flow"].id.get_chunk_info(0).byte_offset
    data = bytearray(path.read_bytes())
    data[offset + 20] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ShardError, match="shard_000000.h5: unreadable"):
        verify_shard(path)


def test_verify_detects_schema_breaks(written):
    root, _ = written
    path = root / "shard_000000.h5"
    with h5py.File(path, "a") as f:
        del f[group_name(1)]["confidence"]
        f[group_name(1)].create_dataset("confidence", data=np.zeros(3, np.float32))
    with pytest.raises(ShardError, match=r"samples/00001/confidence has shape \(3,\), expected \(51,\)"):
        verify_shard(path)
    with h5py.File(path, "a") as f:
        del f[group_name(1)]["confidence"]
        f[group_name(1)].create_dataset("confidence", data=np.zeros(51, np.float32))
        del f[group_name(2)]["cluster"]
    with pytest.raises(ShardError, match="samples/00002/cluster missing"):
        verify_shard(path)
    with h5py.File(path, "a") as f:
        f.attrs["schema_version"] = SCHEMA_VERSION + 1
    with pytest.raises(ShardError, match="schema version"):
        verify_shard(path)


def test_failed_write_leaves_no_file(tmp_path):
    bad = _sample(0, 5, 5, False)
    bad["flow"] = object()  # h5py cannot store it
    with pytest.raises(TypeError):
        write_shard(tmp_path / "shard_000000.h5", [bad], "", "h")
    assert list(tmp_path.iterdir()) == []


def test_index_json_lists_what_the_labelled_shards_hold(reference):
    """label.py's index.json: plain JSON whose records (ids, indices, point counts) are those of the samples inside
    the shard files it lists, in their order."""
    index = json.loads((reference / "index.json").read_text())
    for shard in index["shards"]:
        with h5py.File(reference / shard["file"]) as f:
            held = [
                {
                    "sample_id": str(f[group_name(i)].attrs["sample_id"]),
                    "index": int(f[group_name(i)].attrs["index"]),
                    "n0": len(f[group_name(i)]["pc0"]),
                    "n1": len(f[group_name(i)]["pc1"]),
                }
                for i in range(int(f.attrs["num_samples"]))
            ]
        assert shard["samples"] == held
    assert [s["index"] for shard in index["shards"] for s in shard["samples"]] == [0, 1, 2, 3, 4]


def test_plan_shards_split_is_a_partition():
    full = plan_shards(10, 3)
    assert full == [(0, [0, 1, 2]), (1, [3, 4, 5]), (2, [6, 7, 8]), (3, [9])]
    assert plan_shards(10, 3, limit=5) == [(0, [0, 1, 2]), (1, [3, 4])]
    parts = [plan_shards(10, 3, shard_index=i, num_shards=3) for i in range(3)]
    assert parts == [[(0, [0, 1, 2]), (3, [9])], [(1, [3, 4, 5])], [(2, [6, 7, 8])]]
    assert plan_shards(10, 3, shard_index=1, num_shards=8) == [(1, [3, 4, 5])]
    assert plan_shards(10, 3, shard_index=5, num_shards=8) == []
    with pytest.raises(ValueError, match="shard_index must be in 0..1"):
        plan_shards(10, 3, shard_index=2, num_shards=2)


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_every_compression_round_trips(tmp_path, compression):
    sample = _sample(5, 60, 70, True)
    write_shard(tmp_path / "shard_000000.h5", [sample], "", "h", compression)
    assert verify_shard(tmp_path / "shard_000000.h5", "h", 1) == 1
    with h5py.File(tmp_path / "shard_000000.h5") as f:
        group = f[group_name(0)]
        assert group["pc0"].compression == (None if compression == "none" else compression)
        for key, value in sample.items():
            if key != "attrs":
                np.testing.assert_array_equal(group[key][()], value, err_msg=key)


def test_unknown_compression_is_refused_before_writing(tmp_path):
    with pytest.raises(ValueError, match="^write_shard: compression must be one of none, gzip, lzf, got 'zstd'$"):
        write_shard(tmp_path / "shard_000000.h5", [_sample(0, 5, 5, False)], "", "h", "zstd")
    assert list(tmp_path.iterdir()) == []


def test_reader_refuses_an_index_that_is_not_a_labelling_index(written):
    root, _ = written
    (root / "index.json").write_text(json.dumps({"shards": [{"file": "shard_000000.h5", "samples": [{"index": 0}]}]}))
    with pytest.raises(ValueError, match=r"index.json: not a labelling index \(KeyError: 'sample_id'\)$"):
        ShardDataset(root)


@pytest.mark.parametrize("name", ["../elsewhere/shard_000000.h5", "/tmp/shard_000000.h5", "sub/shard_000000.h5", ".."])
def test_an_index_cannot_list_shards_outside_its_folder(written, tmp_path, name):
    """A label folder from elsewhere whose index.json lists a shard by a path is refused before anything is read
    (a training run would otherwise read files anywhere)."""
    root, _ = written
    index = json.loads((root / "index.json").read_text())
    index["shards"][0]["file"] = name
    (root / "index.json").write_text(json.dumps(index))
    with pytest.raises(ValueError, match=r"index.json: shard .* is not a file of this folder \(no paths allowed\)$"):
        ShardDataset(root)


@pytest.mark.parametrize("key", ["flow", "confidence", "pc0", "gt_flow"])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_verification_refuses_non_finite_values(tmp_path, key, bad):
    """A shard holding NaN or Inf (1 % of one array) is refused in one line naming the array; training reads no
    such label (issue 31: non-finite values are stopped at every door)."""
    sample = _sample(3, 200, 150, True)
    sample[key] = sample[key].copy()
    sample[key][: max(1, len(sample[key]) // 100)] = bad
    path = tmp_path / "shard_000000.h5"
    write_shard(path, [sample], "", "h")
    with pytest.raises(ShardError, match=rf"{group_name(0)}/{key} holds \d+ non-finite value\(s\) \(NaN or Inf\)$"):
        verify_shard(path, "h", 1)
