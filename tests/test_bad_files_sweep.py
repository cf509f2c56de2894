"""A sweep, not a list (issue 31, point 6): every kind of file a user is handed, in each broken form, given to the
entry points that read it. Each case must end in one line naming the file (no traceback, no library log spew), the
entry point's exit status, and nothing written.

Files and readers covered here: an export's ``metadata.json`` and ``fastflow3d.pt2`` (``Predictor.load`` and
``fastflow3d-infer``, which ``eval.py method=[student]`` shares), scans in every format ``fastflow3d-infer`` reads,
ego-motion files, and a label folder's ``index.json`` and shards (``train.py``). Forms: empty, truncated, garbage,
wrong types, a newer format version, a path outside its folder, degenerate content (one point, all identical)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from fastflow3d.artifact import METADATA_NAME, ArtifactError, sha256_file
from fastflow3d.export import export_checkpoint
from fastflow3d.infer import main as infer_main
from fastflow3d.predictor import Predictor
from fastflow3d.training import TrainError, fit
from icpflow.datasets.synthetic import SyntheticDataset

from helpers.shards import write_pseudo_labels
from helpers.training import train_cfg
from students import tiny_checkpoint, tiny_model  # tests/ is on sys.path (pytest prepend import mode)


@pytest.fixture(scope="module")
def pair():
    return SyntheticDataset(split="test", beams=32, num_sequences=1, frames_per_sequence=2, seed=4)[0]


@pytest.fixture(scope="module")
def export_dir(pair, tmp_path_factory):
    root = tmp_path_factory.mktemp("sweep")
    (root / "run" / "checkpoints").mkdir(parents=True)
    checkpoint = tiny_checkpoint(root / "run" / "checkpoints" / "x.ckpt", tiny_model(25.6, 0.8), pair, steps=1)
    return export_checkpoint(checkpoint, formats=("pt2",))


def _broken_bytes(data: bytes, form: str) -> bytes:
    return {
        "empty": b"",
        "truncated": data[: max(0, len(data) // 2 - 3)],
        "garbage": b"\x00\xffnot this format\x13" * 7,
    }[form]


def _metadata_form(metadata: dict, form: str):
    forms = {
        "a list": [metadata],
        "files not a dict": {**metadata, "files": ["fastflow3d.pt2"]},
        "file entry not a dict": {**metadata, "files": {"pt2": "fastflow3d.pt2"}},
        "newer version": {**metadata, "metadata_version": 99},
        "version not a number": {**metadata, "metadata_version": "2"},
        "path outside": {**metadata, "files": {"pt2": {**metadata["files"]["pt2"], "path": "../fastflow3d.pt2"}}},
        "preprocessing not a dict": {**metadata, "preprocessing": "yes"},
    }
    return forms[form]


def _one_line_naming(message: str, path: Path) -> None:
    assert "\n" not in message and "Traceback" not in message, message
    assert str(path) in message or path.name in message, message


def _nothing_written(folder: Path, before: set) -> None:
    assert {p for p in folder.rglob("*")} == before


@pytest.mark.parametrize("name", [METADATA_NAME, "fastflow3d.pt2"])
@pytest.mark.parametrize("form", ["empty", "truncated", "garbage"])
def test_a_damaged_export_file(export_dir, tmp_path, name, form):
    broken = tmp_path / "export"
    shutil.copytree(export_dir, broken)
    target = broken / name
    target.write_bytes(_broken_bytes(target.read_bytes(), form))
    if name != METADATA_NAME:  # as whoever handed it over would: the hash matches the damaged file
        metadata = json.loads((broken / METADATA_NAME).read_text())
        metadata["files"]["pt2"]["sha256"] = sha256_file(target)
        (broken / METADATA_NAME).write_text(json.dumps(metadata))
    before = set(tmp_path.rglob("*"))
    with pytest.raises(ArtifactError) as caught:
        Predictor.load(broken)
    _one_line_naming(str(caught.value), target)
    _nothing_written(tmp_path, before)


@pytest.mark.parametrize(
    "form",
    [
        "a list",
        "files not a dict",
        "file entry not a dict",
        "newer version",
        "version not a number",
        "path outside",
        "preprocessing not a dict",
    ],
)
def test_export_metadata_of_wrong_types_or_versions(export_dir, tmp_path, form):
    broken = tmp_path / "export"
    shutil.copytree(export_dir, broken)
    metadata = json.loads((broken / METADATA_NAME).read_text())
    (broken / METADATA_NAME).write_text(json.dumps(_metadata_form(metadata, form)))
    with pytest.raises(ArtifactError) as caught:
        Predictor.load(broken)
    message = str(caught.value)
    assert "\n" not in message and ("metadata" in message or METADATA_NAME in message), message


def _scan_file(folder: Path, suffix: str, points: np.ndarray) -> Path:
    path = folder / f"scan{suffix}"
    if suffix == ".bin":
        np.column_stack([points, np.zeros(len(points))]).astype(np.float32).tofile(path)
    elif suffix == ".npy":
        np.save(path, points.astype(np.float32))
    elif suffix == ".npz":
        np.savez(path, points=points.astype(np.float32))
    elif suffix == ".pcd":
        header = (
            "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
            f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\nDATA ascii\n"
        )
        path.write_text(header + "\n".join(" ".join(f"{v:.3f}" for v in row) for row in points) + "\n")
    else:  # .ply
        header = f"ply\nformat ascii 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\n"
        header += "property float z\nend_header\n"
        path.write_text(header + "\n".join(" ".join(f"{v:.3f}" for v in row) for row in points) + "\n")
    return path


SCAN_FORMS = ["empty", "truncated", "garbage", "one point", "all identical", "transposed", "not numbers"]


@pytest.mark.parametrize("suffix", [".bin", ".npy", ".npz", ".pcd", ".ply"])
@pytest.mark.parametrize("form", SCAN_FORMS)
def test_a_broken_scan_given_to_the_inference_cli(export_dir, pair, tmp_path, capsys, suffix, form):
    """Exit 2 with one line naming the scan, or (degenerate but valid content: one point, all identical) a result
    that is finite; never a traceback."""
    good = _scan_file(tmp_path, suffix, pair.pc1)
    if form in ("empty", "truncated", "garbage"):
        scan = tmp_path / f"broken{suffix}"
        scan.write_bytes(_broken_bytes(good.read_bytes(), form))
    elif form == "one point":
        scan = _scan_file(tmp_path / "one", suffix, pair.pc0[:1]) if (tmp_path / "one").mkdir() is None else None
    elif form == "all identical":
        (tmp_path / "same").mkdir()
        scan = _scan_file(tmp_path / "same", suffix, np.repeat(pair.pc0[:1], 500, axis=0))
    elif form == "transposed":
        if suffix not in (".npy", ".npz"):
            pytest.skip("a text or raw format has no shape to transpose")
        scan = tmp_path / f"transposed{suffix}"
        (np.save if suffix == ".npy" else lambda p, a: np.savez(p, points=a))(scan, pair.pc0.T.copy())
    else:  # not numbers
        if suffix not in (".npy", ".npz"):
            pytest.skip("a raw or text format holds numbers or fails to parse (the garbage form)")
        scan = tmp_path / f"strings{suffix}"
        values = np.array([["a", "b", "c"]] * 10)
        (np.save if suffix == ".npy" else lambda p, a: np.savez(p, points=a))(scan, values)
    out = tmp_path / "flow.npz"
    ego = tmp_path / "ego.txt"
    ego.write_text(" ".join(f"{v:.9f}" for v in pair.ego1_from_ego0.reshape(-1)) + "\n")
    status = infer_main([str(export_dir), str(scan), str(good), "--ego", str(ego), "--out", str(out), "--no-bev"])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    spew = [
        line for line in err.strip().splitlines() if line and not line.startswith("infer:") and "Warning" not in line
    ]
    assert not spew, err  # no library log lines: our one-line errors and one-line warnings only
    if form in ("one point", "all identical"):
        if status == 0:
            assert np.isfinite(np.load(out)["flow"]).all()
            return
    assert status == 2, err
    lines = [line for line in err.strip().splitlines() if line.startswith("infer:")]
    assert len(lines) == 1 and scan.name in lines[0], err
    assert not out.exists()


@pytest.mark.parametrize("form", ["empty", "truncated", "garbage", "one number", "identity twice"])
def test_a_broken_ego_motion_file(export_dir, pair, tmp_path, capsys, form):
    good = _scan_file(tmp_path, ".npy", pair.pc0)
    ego = tmp_path / "ego.txt"
    text = " ".join(f"{v:.6f}" for v in pair.ego1_from_ego0.reshape(-1))
    ego.write_text(
        {"empty": "", "truncated": text[: len(text) // 2], "garbage": "x y z\n", "one number": "1.0\n"}.get(
            form, "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n"
        )
    )
    out = tmp_path / "flow.npz"
    status = infer_main([str(export_dir), str(good), str(good), "--ego", str(ego), "--out", str(out), "--no-bev"])
    err = capsys.readouterr().err
    assert status == 2 and "Traceback" not in err, err
    lines = [line for line in err.strip().splitlines() if line.startswith("infer:")]
    assert len(lines) == 1 and ego.name in lines[0], err
    assert not out.exists()


@pytest.fixture(scope="module")
def labels(pair, tmp_path_factory):
    return write_pseudo_labels(tmp_path_factory.mktemp("labels") / "train", [pair, pair])


@pytest.mark.parametrize(
    "form",
    ["empty", "truncated", "garbage", "shards not a list", "samples not a list", "shard outside", "no shards"],
)
def test_a_broken_index_given_to_train(labels, tmp_path, form):
    folder = tmp_path / "labels"
    shutil.copytree(labels, folder)
    index_path = folder / "index.json"
    index = json.loads(index_path.read_text())
    if form in ("empty", "truncated", "garbage"):
        index_path.write_bytes(_broken_bytes(index_path.read_bytes(), form))
    else:
        changed = {
            "shards not a list": {**index, "shards": "all"},
            "samples not a list": {**index, "shards": [{**index["shards"][0], "samples": 3}]},
            "shard outside": {**index, "shards": [{**index["shards"][0], "file": "../other.h5"}]},
            "no shards": {**index, "shards": []},
        }[form]
        index_path.write_text(json.dumps(changed))
    with pytest.raises(TrainError) as caught:
        fit(train_cfg(tmp_path, folder, folder, "trainer.max_steps=1"))
    _one_line_naming(str(caught.value), folder)
    assert not (tmp_path / "run" / "checkpoints").exists()


@pytest.mark.parametrize("form", ["empty", "truncated", "garbage"])
def test_a_broken_shard_given_to_train(labels, tmp_path, form):
    folder = tmp_path / "labels"
    shutil.copytree(labels, folder)
    shard = sorted(folder.glob("shard_*.h5"))[0]
    shard.write_bytes(_broken_bytes(shard.read_bytes(), form))
    with pytest.raises(TrainError) as caught:
        fit(train_cfg(tmp_path, folder, folder, "trainer.max_steps=1"))
    _one_line_naming(str(caught.value), shard)
    assert not (tmp_path / "run" / "checkpoints").exists()


@pytest.mark.parametrize("form", ["empty", "truncated", "garbage", "a pickle", "not a training checkpoint"])
def test_a_broken_checkpoint_given_to_export_and_the_predictor(pair, tmp_path, form):
    """export.py (``export_checkpoint``) and ``Predictor.load`` (eval.py's student) on a damaged or foreign
    ``.ckpt``: one line naming it, nothing written beside it, a pickle never run."""
    import pickle

    import torch

    from fastflow3d.checkpoint import CheckpointError
    from fastflow3d.export import ExportError

    run = tmp_path / "run" / "checkpoints"
    run.mkdir(parents=True)
    good = tiny_checkpoint(run / "good.ckpt", tiny_model(25.6, 0.8), pair, steps=1)
    broken = run / "broken.ckpt"
    target = tmp_path / "pwned"
    if form == "a pickle":

        class Payload:
            def __reduce__(self):
                return (open, (str(target), "w"))

        torch.save({"state_dict": Payload()}, broken, pickle_protocol=pickle.HIGHEST_PROTOCOL)
    elif form == "not a training checkpoint":
        torch.save({"weights": torch.zeros(3)}, broken)
    else:
        broken.write_bytes(_broken_bytes(good.read_bytes(), form))
    before = set(tmp_path.rglob("*"))
    for load in (lambda: export_checkpoint(broken, formats=("pt2",)), lambda: Predictor.load(broken)):
        with pytest.raises((CheckpointError, ExportError, ArtifactError)) as caught:
            load()
        _one_line_naming(str(caught.value), broken)
    _nothing_written(tmp_path, before)
    assert not target.exists()
