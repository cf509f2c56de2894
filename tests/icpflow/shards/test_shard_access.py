"""Shards cannot read outside their label folder, nor claim memory they do not hold (issue 45): every reader
(verification, the training and evaluation dataset, read_shard_samples) refuses, in one line naming the file and
the array, a link to another file, storage outside the shard, a virtual dataset, a shard that is a symbolic link or
a FIFO, and arrays over the cap or larger than the file; no such read hangs or allocates."""

import os

import h5py
import numpy as np
import pytest
from test_shards import _sample

from icpflow.shards import ShardDataset, ShardError, verify_shard
from icpflow.shards.access import MAX_POINTS
from icpflow.shards.reader import read_shard_samples
from icpflow.shards.schema import group_name

from helpers.shards import write_labels

NAME = "shard_000000.h5"


def _replace(path, key, make):
    """Sample 0's array ``key`` replaced by what ``make(group, key, like)`` creates (``like``: the old array)."""
    with h5py.File(path, "a") as handle:
        group = handle[group_name(0)]
        like = group[key][()]
        del group[key]
        make(group, key, like, path.parent)


def _external_link(group, key, like, folder):
    with h5py.File(folder.parent / "elsewhere.h5", "w") as other:
        other["data"] = like
    group[key] = h5py.ExternalLink(str(folder.parent / "elsewhere.h5"), "/data")


def _soft_link(group, key, like, folder):
    group[key] = h5py.SoftLink(f"/{group_name(0)}/flow")


def _external_storage(group, key, like, folder):
    secret = folder.parent / "secret.txt"
    secret.write_bytes(b"root:x:0:0:root:/root:/bin/bash\n" * 64)
    group.create_dataset(key, shape=like.shape, dtype=like.dtype, external=[(str(secret), 0, h5py.h5f.UNLIMITED)])


def _fifo_storage(group, key, like, folder):
    fifo = folder.parent / "pipe"
    os.mkfifo(fifo)
    group.create_dataset(key, shape=like.shape, dtype=like.dtype, external=[(str(fifo), 0, h5py.h5f.UNLIMITED)])


def _virtual(group, key, like, folder):
    with h5py.File(folder.parent / "source.h5", "w") as other:
        other["data"] = like
    layout = h5py.VirtualLayout(shape=like.shape, dtype=like.dtype)
    layout[...] = h5py.VirtualSource(str(folder.parent / "source.h5"), "data", shape=like.shape)
    group.create_virtual_dataset(key, layout)


def _bomb_compressed(group, key, like, folder):  # 3e8 points of zeros in a few kilobytes: never allocated
    group.create_dataset(key, shape=(300_000_000,), dtype=like.dtype, chunks=(1_000_000,), compression="gzip")


def _bomb_raw(group, key, like, folder):  # uncompressed, chunks never written: more bytes than the file holds
    group.create_dataset(key, shape=(MAX_POINTS,), dtype=like.dtype, chunks=(100_000,))


def _wide_values(group, key, like, folder):  # 1 MB per value: a few thousand "points" are gigabytes
    group.create_dataset(key, shape=(4096,), dtype=np.dtype((np.uint8, (1 << 20,))), compression="gzip")


FORMS = {
    "external link": (_external_link, r"is an external link to .*elsewhere.h5:/data"),
    "soft link": (_soft_link, r"is a link to /"),
    "external storage": (_external_storage, r"is stored outside the shard, in '.*secret.txt'"),
    "external storage in a FIFO": (_fifo_storage, r"is stored outside the shard, in '.*pipe'"),
    "virtual dataset": (_virtual, r"is a virtual dataset over .*source.h5"),
    "compressed bomb": (_bomb_compressed, r"claims \(300000000,\) values, over the cap of 5000000 points"),
    "uncompressed bomb": (_bomb_raw, r"claims \(5000000,\) values, more than the file holds"),
    "values of a megabyte": (_wide_values, r"holds .* values, not the plain numbers of a shard"),
}


@pytest.fixture
def labels(tmp_path):
    root = tmp_path / "labels"
    write_labels(root, {NAME: [_sample(0, 300, 280, True)]}, "teacher: {}\n", "h")
    return root


def _every_reader(root):
    """Each reader of a shard, as a call."""
    return {
        "verify_shard": lambda: verify_shard(root / NAME, "h", 1),
        "ShardDataset.verify": lambda: ShardDataset(root).verify(),
        "ShardDataset[0]": lambda: ShardDataset(root)[0],
        "read_shard_samples": lambda: read_shard_samples(root / NAME),
    }


@pytest.mark.timeout(60)  # a FIFO read would hang
@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("key", ["confidence", "gt_flow"])
def test_every_reader_refuses_an_array_that_reads_elsewhere_or_claims_too_much(labels, form, key):
    make, message = FORMS[form]
    _replace(labels / NAME, key, make)
    for reader, call in _every_reader(labels).items():
        with pytest.raises(ShardError, match=rf"{NAME}: {group_name(0)}/{key} {message}") as error:
            call()
        assert "\n" not in str(error.value), reader


@pytest.mark.timeout(60)
def test_a_shard_that_is_a_symbolic_link_or_a_fifo_is_refused(labels, tmp_path):
    elsewhere = tmp_path / "elsewhere.h5"
    os.replace(labels / NAME, elsewhere)
    os.symlink(elsewhere, labels / NAME)
    for reader, call in _every_reader(labels).items():
        with pytest.raises(ShardError, match=rf"{NAME}: a symbolic link \(to .*elsewhere.h5\)"):
            call()
            pytest.fail(reader)
    (labels / NAME).unlink()
    os.mkfifo(labels / NAME)
    for reader, call in _every_reader(labels).items():
        with pytest.raises(ShardError, match=rf"{NAME}: not a regular file"):
            call()
            pytest.fail(reader)


def test_a_sound_shard_still_reads(labels):
    sample = ShardDataset(labels)[0]
    assert sample["pc0"].shape == (300, 3) and verify_shard(labels / NAME, "h", 1) == 1
    assert np.array_equal(read_shard_samples(labels / NAME)[0]["flow"], sample["flow"])


@pytest.mark.parametrize("version", [99, None])
def test_every_reader_refuses_a_shard_of_another_schema_version(labels, version):
    """Issue 45.7: eval.py method=shards read a shard of an unknown schema version without a word."""
    from icpflow.evaluation.methods import ShardMethod

    with h5py.File(labels / NAME, "a") as handle:
        if version is None:
            del handle.attrs["schema_version"]
        else:
            handle.attrs["schema_version"] = version
    expected = "schema version 99, expected 1" if version else "no schema version"
    readers = _every_reader(labels)
    method = ShardMethod(labels)
    readers["eval.py method=shards"] = lambda: method.shards[0]
    for reader, call in readers.items():
        with pytest.raises(ShardError, match=rf"{NAME}: {expected}"):
            call()
            pytest.fail(reader)
