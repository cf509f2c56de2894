"""The one atomic-write helper: a finished write replaces the target; a failed one leaves no trace."""

import errno
import os

import pytest

from icpflow.core.atomic import WriteError, atomic_path, temporary_name, write_text_atomic


def test_a_finished_write_replaces_the_target_and_leaves_no_temporary(tmp_path):
    target = tmp_path / "result.json"
    target.write_text("old")
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".json" and tmp.name.startswith("result.json.tmp-")
        tmp.write_text("new")
        assert target.read_text() == "old"  # the target changes only when the write is complete
    assert target.read_text() == "new"
    assert os.listdir(tmp_path) == ["result.json"]


def test_a_failing_write_leaves_no_temporary_and_no_partial_target(tmp_path):
    fresh, existing = tmp_path / "fresh.h5", tmp_path / "existing.txt"
    existing.write_text("complete")
    for target in (fresh, existing):
        with pytest.raises(RuntimeError, match="disk full"), atomic_path(target) as tmp:
            tmp.write_bytes(b"half of it")
            raise RuntimeError("disk full")
    assert not fresh.exists() and existing.read_text() == "complete"
    assert os.listdir(tmp_path) == ["existing.txt"]


def test_a_writer_that_writes_nothing_leaves_the_target_alone(tmp_path):
    target = tmp_path / "render.png"
    with pytest.raises(WriteError, match="render.png: cannot write"), atomic_path(target):
        pass
    assert os.listdir(tmp_path) == []


def test_a_full_disk_is_one_write_error_naming_the_target(tmp_path):
    """An OSError while writing (here ENOSPC) is one WriteError naming the target and the cause; nothing is left."""
    target = tmp_path / "shard_000000.h5"
    with pytest.raises(WriteError) as caught, atomic_path(target) as tmp:
        tmp.write_bytes(b"partial")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert str(caught.value) == f"{target}: cannot write (No space left on device)"
    assert os.listdir(tmp_path) == []


def test_write_text_makes_the_folder_when_asked(tmp_path):
    target = tmp_path / "a" / "b" / "metrics.csv"
    write_text_atomic(target, "x,y\n1,2\n", make_parents=True)
    assert target.read_text() == "x,y\n1,2\n" and os.listdir(target.parent) == ["metrics.csv"]


@pytest.mark.parametrize("name", ["a" * 214 + ".npz", "b" * 251 + ".npz", "é" * 125 + ".json", "c" * 255])
def test_every_name_that_can_be_written_has_a_temporary_one(tmp_path, name):
    """A scan named with 210+ characters gives an output name the temporary suffix would push over the 255 bytes a
    file name may hold: the temporary name is cut, the target keeps its whole name."""
    target = tmp_path / name
    write_text_atomic(target, "x")
    assert target.read_text() == "x" and [path.name for path in tmp_path.iterdir()] == [name]
    temporary = temporary_name(target)
    assert len(temporary.name.encode()) <= 255 and (not target.suffix or temporary.suffix == target.suffix)
