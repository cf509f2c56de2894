"""A sweep, not a list (issue 31, point 6): every kind of file a user is handed, in each broken form, given to the
entry points that read it. Each case must end in one line naming the file (no traceback, no library log spew), the
entry point's exit status, and nothing written.

Files and readers covered here: an export's ``metadata.json`` and ``fastflow3d.pt2`` (``Predictor.load`` and
``fastflow3d-infer``, which ``eval.py method=[student]`` shares), scans in every format ``fastflow3d-infer`` reads,
ego-motion files, a scan folder's scans and poses file and a folder of ``.npz`` pairs (``label.py``: a broken sample
fails alone and the others are labelled; a broken poses file stops the run before anything is written), and a label
folder's ``index.json`` and shards (``train.py``). Forms: empty, truncated, garbage,
wrong types, a newer format version, a path outside its folder, degenerate content (one point, all identical)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from fastflow3d.artifact.export import export_checkpoint
from fastflow3d.artifact.file_format import METADATA_NAME, ArtifactError, sha256_file
from fastflow3d.inference.cli import main as infer_main
from fastflow3d.inference.predictor import Predictor
from fastflow3d.training.run_folder import TrainError
from fastflow3d.training.trainer import fit
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.labelling.cli import label

from helpers.labelling import REPO, read_samples
from helpers.shards import write_pseudo_labels
from helpers.training import train_cfg


@pytest.fixture(scope="module")
def pair():
    return SyntheticDataset(split="test", beams=32, num_sequences=1, frames_per_sequence=2, seed=4)[0]


@pytest.fixture(scope="module")
def export_dir(tiny_pt2_export):
    return tiny_pt2_export


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
        "input not a dict": {**metadata, "input": "yes"},
        "input of a newer version": {**metadata, "input": {**metadata["input"], "version": 9}},
        "input grid wrong": {**metadata, "input": {**metadata["input"], "grid": {"cell": -1}}},
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
        "input not a dict",
        "input of a newer version",
        "input grid wrong",
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
def test_a_broken_checkpoint_given_to_export_and_the_predictor(tiny_student, tmp_path, form):
    """export.py (``export_checkpoint``) and ``Predictor.load`` (eval.py's student) on a damaged or foreign
    ``.ckpt``: one line naming it, nothing written beside it, a pickle never run."""
    import pickle

    import torch

    from fastflow3d.artifact.checkpoint import CheckpointError
    from fastflow3d.artifact.export import ExportError

    run = tmp_path / "run" / "checkpoints"
    run.mkdir(parents=True)
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
        broken.write_bytes(_broken_bytes(tiny_student.read_bytes(), form))
    before = set(tmp_path.rglob("*"))
    for load in (lambda: export_checkpoint(broken, formats=("pt2",)), lambda: Predictor.load(broken)):
        with pytest.raises((CheckpointError, ExportError, ArtifactError)) as caught:
            load()
        _one_line_naming(str(caught.value), broken)
    _nothing_written(tmp_path, before)
    assert not target.exists()


# ------------------------------------------------------------------------------------------- label.py's inputs
#: the sensor's height over the synthetic world's ground: scans of a folder are in the sensor's frame
SENSOR_HEIGHT = 1.9


def _label(out: Path, dataset: str, root: Path, capfd, *overrides) -> tuple[int, str]:
    """``label.py dataset=<dataset> dataset.root=<root>`` in this process: (exit status, stderr)."""
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(
            "label", [f"dataset={dataset}", f"dataset.root={root}", f"out_dir={out}", "workers=1", *overrides]
        )
    status = label(cfg, progress=False)
    err = capfd.readouterr().err
    assert "Traceback" not in err, err
    return status, err


@pytest.fixture(scope="module")
def scans():
    """Four consecutive synthetic scans in the sensor's frame (16 beams, 2 degrees: the teacher is quick)."""
    world = SyntheticDataset(split="test", beams=16, azimuth_resolution_deg=2.0, num_sequences=1, frames_per_sequence=4)
    clouds = [world.pair(i).pc0 for i in range(3)] + [world.pair(2).pc1]
    return [cloud + np.float32([0, 0, SENSOR_HEIGHT]) for cloud in clouds]


def _scan_folder(folder: Path, scans, suffix: str) -> Path:
    folder.mkdir()
    for index, points in enumerate(scans):
        _scan_file(folder, suffix, points).rename(folder / f"{index:06d}{suffix}")
    np.savetxt(folder / "poses.txt", np.tile(np.eye(4)[:3].reshape(1, -1), (len(scans), 1)))
    return folder


def _break_scan(path: Path, form: str, pair) -> None:
    """Replace the scan at ``path`` by its ``form`` (the forms of SCAN_FORMS)."""
    if form in ("empty", "truncated", "garbage"):
        path.write_bytes(_broken_bytes(path.read_bytes(), form))
    elif form in ("one point", "all identical"):
        points = pair.pc0[:1] if form == "one point" else np.repeat(pair.pc0[:1], 500, axis=0)
        _scan_file(path.parent / "x", path.suffix, points).rename(path) if (path.parent / "x").mkdir() is None else None
    elif form == "transposed":
        np.save(path, pair.pc0.T.copy())
    else:  # not numbers
        np.save(path, np.array([["a", "b", "c"]] * 10))


@pytest.mark.parametrize(
    "suffix, form",
    [(suffix, form) for suffix in (".bin", ".npy", ".pcd", ".ply") for form in ("empty", "truncated", "garbage")]
    + [(".npy", form) for form in ("one point", "all identical", "transposed", "not numbers")],
)
def test_a_broken_scan_in_a_scan_folder_given_to_label(scans, pair, tmp_path, capfd, suffix, form):
    """The third of four scans broken: the two pairs that need it fail, each with one line naming it (exit 1,
    failures.jsonl); the first pair is labelled all the same (nothing lost). Degenerate content may label."""
    folder = _scan_folder(tmp_path / "scans", scans, suffix)
    broken = folder / f"000002{suffix}"
    _break_scan(broken, form, pair)
    out = tmp_path / "labels"
    status, err = _label(out, "sequence", folder, capfd, f"dataset.reader.sensor_height={SENSOR_HEIGHT}")
    samples = {sample["sample_id"] for sample in read_samples(out)}
    assert "000000" in samples, err  # the pair that does not need the broken scan
    if form in ("one point", "all identical") and status == 0:
        return
    assert status == 1, err
    failed = [line for line in err.splitlines() if line.strip().startswith("failed ")]
    assert len(failed) == 2 and all(str(broken) in line for line in failed), err
    assert all(line.count(str(broken)) >= 1 and "\n" not in line for line in failed)
    records = [json.loads(line) for line in (out / "failures.jsonl").read_text().splitlines()]
    assert sorted(record["sample_id"] for record in records) == ["000001", "000002"]


@pytest.mark.parametrize(
    "form", ["empty", "truncated", "garbage", "one number", "too few poses", "not rigid", "npy of strings"]
)
def test_a_broken_poses_file_given_to_label(scans, tmp_path, capfd, form):
    """A poses file that cannot give every scan its pose stops label.py before any work: exit 2, one line naming
    the file, nothing written."""
    folder = _scan_folder(tmp_path / "scans", scans, ".npy")
    poses = folder / "poses.txt"
    text = poses.read_text()
    if form == "npy of strings":
        poses.unlink()
        poses = folder / "poses.npy"
        np.save(poses, np.array([["a"] * 4] * 4))
    else:
        lines = text.splitlines()
        poses.write_text(
            {
                "empty": "",
                "truncated": text[: len(text) // 2 - 7],
                "garbage": "\x00\xff poses? \x13\n" * 4,
                "one number": "1.0\n",
                "too few poses": "\n".join(lines[:2]) + "\n",
                "not rigid": "\n".join(["2 0 0 0 0 2 0 0 0 0 2 0"] * len(lines)) + "\n",
            }[form]
        )
    out = tmp_path / "labels"
    status, err = _label(
        out,
        "sequence",
        folder,
        capfd,
        f"dataset.reader.sensor_height={SENSOR_HEIGHT}",
        f"dataset.reader.poses_file={poses}",
    )
    assert status == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("label: ") and poses.name in lines[0], err
    assert not out.exists() or not any(out.iterdir())


PAIR_FORMS = ["empty", "truncated", "garbage", "one point", "flow of other length", "strings", "flow not finite"]


@pytest.mark.parametrize("form", PAIR_FORMS)
def test_a_broken_pair_file_given_to_label(pair, tmp_path, capfd, form):
    """A folder of ``.npz`` pairs (dataset=pairs) with one broken: it fails alone with one line naming it; the
    good pair is labelled (exit 1). A pair of one point may label."""
    folder = tmp_path / "pairs" / "train"
    folder.mkdir(parents=True)
    arrays = {"pc0": pair.pc0, "pc1": pair.pc1, "pose0": np.eye(4), "pose1": pair.ego1_from_ego0}
    np.savez(folder / "a.npz", **arrays)
    broken = folder / "b.npz"
    if form in ("empty", "truncated", "garbage"):
        broken.write_bytes(_broken_bytes((folder / "a.npz").read_bytes(), form))
    else:
        changed = {
            "one point": {"pc0": pair.pc0[:1]},
            "flow of other length": {"flow": np.zeros((3, 3), np.float32)},
            "strings": {"pc1": np.array([["a", "b", "c"]] * 5)},
            "flow not finite": {"flow": np.full(pair.pc0.shape, np.nan, np.float32)},
        }[form]
        np.savez(broken, **{**arrays, **changed})
    out = tmp_path / "labels"
    status, err = _label(out, "pairs", tmp_path / "pairs", capfd)
    samples = {sample["sample_id"] for sample in read_samples(out)}
    assert "a" in samples, err
    if form == "one point" and status == 0:
        return
    assert status == 1, err
    failed = [line for line in err.splitlines() if line.strip().startswith("failed ")]
    assert len(failed) == 1 and broken.name in failed[0], err


# ----------------------------------------------------------------------------------- eval.py's and resumes' inputs
EVAL_SMALL = ["dataset.reader.num_sequences=1", "dataset.reader.frames_per_sequence=2", "dataset.reader.beams=32"]


def _eval(out: Path, capfd, *overrides) -> tuple[int, str]:
    """eval.py's body (``run_eval`` inside ``reported``, as eval.py runs it) on a small synthetic split."""
    from fastflow3d.inference.eval_methods import student_method
    from icpflow.core.errors_and_signals import reported
    from icpflow.evaluation import run_eval

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("eval", [*EVAL_SMALL, "bev=0", f"out_dir={out}", *overrides])
    with pytest.raises(SystemExit) as stopped, reported("eval"):
        status = run_eval(cfg, progress=False, extra_methods={"student": student_method})
        raise SystemExit(status)
    err = capfd.readouterr().err
    assert "Traceback" not in err and "unexpected" not in err, err
    return stopped.value.code, err


@pytest.mark.parametrize("form", ["metadata garbage", "pt2 truncated", "path outside", "newer version"])
def test_a_broken_export_given_to_eval(export_dir, tmp_path, capfd, form):
    """``eval.py method=[student] checkpoint=<export>``: exit 2, one line naming the file, no metrics written."""
    broken = tmp_path / "export"
    shutil.copytree(export_dir, broken)
    metadata = json.loads((broken / METADATA_NAME).read_text())
    if form == "metadata garbage":
        named = broken / METADATA_NAME
        named.write_bytes(_broken_bytes(named.read_bytes(), "garbage"))
    elif form == "pt2 truncated":
        named = broken / "fastflow3d.pt2"
        named.write_bytes(_broken_bytes(named.read_bytes(), "truncated"))
        metadata["files"]["pt2"]["sha256"] = sha256_file(named)
        (broken / METADATA_NAME).write_text(json.dumps(metadata))
    else:
        named = broken / METADATA_NAME
        (broken / METADATA_NAME).write_text(json.dumps(_metadata_form(metadata, form)))
    out = tmp_path / "scores"
    status, err = _eval(out, capfd, "method=[student]", f"checkpoint={broken}")
    lines = [line for line in err.splitlines() if line.strip()]
    assert status == 2 and len(lines) == 1 and lines[0].startswith("eval: "), err
    assert named.name in lines[0] or str(broken) in lines[0], err
    assert not list(out.rglob("metrics*.json"))


@pytest.mark.parametrize("form", ["index garbage", "shard truncated", "shard outside"])
def test_a_broken_label_folder_given_to_eval(labels, tmp_path, capfd, form):
    """``eval.py method=[shards] shards=<label folder>``: exit 2, one line naming the folder or shard, no metrics."""
    folder = tmp_path / "labels"
    shutil.copytree(labels, folder)
    if form == "index garbage":
        named = folder / "index.json"
        named.write_bytes(_broken_bytes(named.read_bytes(), "garbage"))
    elif form == "shard truncated":
        named = sorted(folder.glob("shard_*.h5"))[0]
        named.write_bytes(_broken_bytes(named.read_bytes(), "truncated"))
    else:
        named = folder / "index.json"
        index = json.loads(named.read_text())
        named.write_text(json.dumps({**index, "shards": [{**index["shards"][0], "file": "/etc/passwd"}]}))
    out = tmp_path / "scores"
    status, err = _eval(out, capfd, "method=[shards]", f"shards={folder}")
    lines = [line for line in err.splitlines() if line.strip()]
    assert status == 2 and len(lines) == 1, err
    assert str(folder) in lines[0], err
    assert not list(out.rglob("metrics*.json"))


@pytest.mark.parametrize("form", ["empty", "truncated", "garbage", "not a training checkpoint"])
def test_a_broken_checkpoint_to_resume_from_loses_nothing(labels, tmp_path, form):
    """``train.py ckpt_path=<file>`` with a damaged or foreign checkpoint: one line naming it, and the run folder's
    existing checkpoints are left exactly as they were (nothing lost)."""
    import torch

    fit(train_cfg(tmp_path, labels, labels, "trainer.max_steps=1"))
    checkpoints = tmp_path / "run" / "checkpoints"
    before = {path: path.read_bytes() for path in checkpoints.iterdir()}
    assert (checkpoints / "last.ckpt") in before
    broken = tmp_path / "broken.ckpt"
    if form == "not a training checkpoint":
        torch.save({"weights": torch.zeros(3)}, broken)
    else:
        broken.write_bytes(_broken_bytes((checkpoints / "last.ckpt").read_bytes(), form))
    with pytest.raises(TrainError) as caught:
        fit(train_cfg(tmp_path, labels, labels, "trainer.max_steps=2", f"ckpt_path={broken}"))
    _one_line_naming(str(caught.value), broken)
    assert {path: path.read_bytes() for path in checkpoints.iterdir()} == before


def _bomb(folder: Path, suffix: str) -> Path:
    """A small scan file that claims 6e6 points (over icpflow.core.frame_pair.MAX_POINTS): a zip of zeros, a bare
    header, a
    PLY whose vertices hold a list (sizes vary: it could claim anything), a PCD header."""
    import zipfile

    path = folder / f"bomb{suffix}"
    header = np.lib.format.header_data_from_array_1_0(np.zeros((1, 3), np.float32))
    header["shape"] = (6_000_000, 3)
    if suffix == ".npz":
        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive, archive.open("points.npy", "w") as member:
            np.lib.format.write_array_header_1_0(member, header)
            zeros = bytes(12_000_000)
            for _ in range(6):
                member.write(zeros)
    elif suffix == ".npy":
        with open(path, "wb") as handle:
            np.lib.format.write_array_header_1_0(handle, header)
            handle.write(bytes(1000))
    elif suffix == ".ply":
        path.write_bytes(
            b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000\nproperty float x\nproperty float y\n"
            b"property float z\nproperty list uchar int ids\nend_header\n" + bytes(100)
        )
    else:  # .pcd
        path.write_text(
            "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 6000000\nHEIGHT 1\n"
            "POINTS 6000000\nDATA binary\n"
        )
    return path


@pytest.mark.parametrize("suffix", [".npz", ".npy", ".ply", ".pcd"])
def test_a_scan_that_claims_more_than_it_holds_is_refused_before_allocating(export_dir, pair, tmp_path, capsys, suffix):
    """Issue 45's resource bombs: each refused in one line naming the file, by the inference CLI and by a scan
    folder's reader (label.py dataset=sequence), the process's peak memory grown by less than 200 MB."""
    import resource

    from icpflow.core.frame_pair import FramePairError
    from icpflow.datasets.scan_folder import ScanSequenceDataset

    bomb = _bomb(tmp_path, suffix)
    good = _scan_file(tmp_path, ".npy", pair.pc1)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    out = tmp_path / "flow.npz"
    status = infer_main([str(export_dir), str(bomb), str(good), "--out", str(out), "--no-bev"])
    err = capsys.readouterr().err
    assert status == 2 and not out.exists(), err
    lines = [line for line in err.strip().splitlines() if line.startswith("infer:")]
    assert len(lines) == 1 and bomb.name in lines[0], err
    assert "over the cap" in lines[0] or "not a point cloud of fixed-size rows" in lines[0], err
    if suffix != ".npz":  # a scan folder holds .bin, .npy, .ply or .pcd
        folder = tmp_path / "folder"
        folder.mkdir()
        bomb.rename(folder / f"000001{suffix}")
        _scan_file(folder, suffix, pair.pc0).rename(folder / f"000000{suffix}")
        with pytest.raises(FramePairError, match=r"000001.* (over the cap|more than|list)") as error:
            ScanSequenceDataset(folder, sensor_height=0.0).pair(0)
        assert "\n" not in str(error.value)
    assert (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak) * 1024 < 200e6


def test_the_cap_is_the_environments_where_it_says_one(tmp_path):
    """ICPFLOW_MAX_POINTS raises (or lowers) the cap for a denser sensor: the 6e6-point claim then passes the cap
    and is refused for what the file holds, still one line naming it, nothing allocated."""
    import os
    import subprocess
    import sys

    bomb = _bomb(tmp_path, ".npy")
    code = (
        "import sys; from icpflow.datasets.file_formats import load_npy; "
        "load_npy(__import__('pathlib').Path(sys.argv[1]))"
    )
    for cap, words in (("7000000", "more than the file's"), ("1000", "over the cap of 1000")):
        result = subprocess.run(
            [sys.executable, "-c", code, str(bomb)],
            env={**os.environ, "ICPFLOW_MAX_POINTS": cap},
            capture_output=True,
            text=True,
            cwd=REPO,
        )
        assert result.returncode != 0 and words in result.stderr.strip().splitlines()[-1], result.stderr
