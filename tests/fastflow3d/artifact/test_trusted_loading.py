"""Model files from elsewhere are data, never code (issue 31, point 1): crafted ``.pt2`` archives, metadata that
points outside its export folder and TorchScript are refused in one line before anything is unpickled; every
payload here would create a file in the test's temporary folder, and the tests assert it is absent."""

from __future__ import annotations

import io
import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from fastflow3d.artifact.export import export_checkpoint
from fastflow3d.artifact.file_format import METADATA_NAME, ArtifactError, sha256_file
from fastflow3d.artifact.safe_loading import check_pt2
from fastflow3d.inference.predictor import Predictor
from icpflow.datasets.synthetic.reader import SyntheticDataset

from helpers.students import place_checkpoint  # tests/ is on sys.path (pytest prepend import mode)


class Payload:
    """Unpickled, it opens ``target`` for writing (creating it): what an attacker's code would do first."""

    def __init__(self, target: Path):
        self.target = str(target)

    def __reduce__(self):
        return (open, (self.target, "w"))


@pytest.fixture(scope="module")
def export_dir(tiny_pt2_export):
    return tiny_pt2_export


def _rewrite_pt2(source: Path, target_dir: Path, change) -> Path:
    """A copy of the export folder ``source`` whose ``.pt2`` members pass through ``change(name, bytes) -> {name:
    bytes}`` (a member may be replaced, dropped or joined by others), with ``metadata.json``'s sha256 rewritten as
    an attacker would."""
    crafted = target_dir / "crafted"
    shutil.copytree(source, crafted)
    pt2 = crafted / "fastflow3d.pt2"
    members = {}
    with zipfile.ZipFile(source / "fastflow3d.pt2") as archive:
        for name in archive.namelist():
            members.update(change(name, archive.read(name)))
    with zipfile.ZipFile(pt2, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)
    metadata = json.loads((crafted / METADATA_NAME).read_text())
    metadata["files"]["pt2"]["sha256"] = sha256_file(pt2)
    (crafted / METADATA_NAME).write_text(json.dumps(metadata))
    return crafted


def _pickled(target: Path) -> bytes:
    buffer = io.BytesIO()
    torch.save(Payload(target), buffer)
    return buffer.getvalue()


def _refused(path: Path, words: str, target: Path) -> None:
    with pytest.raises(ArtifactError, match=words) as caught:
        Predictor.load(path)
    assert "\n" not in str(caught.value) and str(path) in str(caught.value)
    assert not target.exists(), "the payload ran"


def test_an_own_export_passes_the_check(export_dir):
    check_pt2(export_dir / "fastflow3d.pt2")
    assert Predictor.load(export_dir).backend == "pt2"


def test_a_pickled_weight_is_refused_before_torch_unpickles_it(export_dir, tmp_path):
    target = tmp_path / "pwned"

    def change(name, data):
        if name.endswith("model_weights_config.json"):
            config = json.loads(data)
            first = next(iter(config["config"].values()))
            first["use_pickle"] = True
            return {name: json.dumps(config).encode()}
        if name.endswith("data/weights/weight_0"):
            return {name: _pickled(target)}
        return {name: data}

    crafted = _rewrite_pt2(export_dir, tmp_path, change)
    _refused(crafted, "stored pickled", target)
    # the threat is real: torch's own loader runs it
    try:
        torch.export.load(str(crafted / "fastflow3d.pt2"))
    except Exception:
        pass
    assert target.exists()


def test_sample_inputs_that_need_full_unpickling_are_refused(export_dir, tmp_path):
    target = tmp_path / "pwned"

    def change(name, data):
        return {name: _pickled(target) if "/data/sample_inputs/" in name else data}

    _refused(_rewrite_pt2(export_dir, tmp_path, change), "not plain tensors", target)


@pytest.mark.parametrize("member", ["archive/data/aotinductor/model/model.so", "archive/extra/evil.pkl"])
def test_members_an_exported_program_does_not_hold_are_refused(export_dir, tmp_path, member):
    def change(name, data):
        return {name: data, **({member: b"\x7fELF"} if name.endswith("archive_version") else {})}

    _refused(_rewrite_pt2(export_dir, tmp_path, change), "not part of an exported program", tmp_path / "pwned")


def test_a_pt2_that_is_no_archive_is_one_line(export_dir, tmp_path):
    crafted = tmp_path / "crafted"
    shutil.copytree(export_dir, crafted)
    (crafted / "fastflow3d.pt2").write_bytes(b"not a zip")
    metadata = json.loads((crafted / METADATA_NAME).read_text())
    metadata["files"]["pt2"]["sha256"] = sha256_file(crafted / "fastflow3d.pt2")
    (crafted / METADATA_NAME).write_text(json.dumps(metadata))
    _refused(crafted, "not a torch.export archive", tmp_path / "pwned")


@pytest.mark.parametrize(
    "entry, words",
    [
        ({"path": "../elsewhere.pt2"}, "leaves the export folder"),
        ({"path": "sub/fastflow3d.pt2"}, "leaves the export folder"),
        ({"path": "/tmp/fastflow3d.pt2"}, "leaves the export folder"),
        ({"path": ".."}, "leaves the export folder"),
        ("fastflow3d.pt2", "must be an object with a 'path' string"),
        ({"path": 3}, "must be an object with a 'path' string"),
    ],
)
def test_metadata_cannot_point_outside_its_folder(export_dir, tmp_path, entry, words):
    outside = tmp_path / "elsewhere.pt2"
    shutil.copy(export_dir / "fastflow3d.pt2", outside)
    crafted = tmp_path / "export"
    shutil.copytree(export_dir, crafted)
    metadata = json.loads((crafted / METADATA_NAME).read_text())
    if isinstance(entry, dict) and isinstance(entry.get("path"), str):
        entry = {**entry, "sha256": sha256_file(outside)}
    metadata["files"]["pt2"] = entry
    (crafted / METADATA_NAME).write_text(json.dumps(metadata))
    with pytest.raises(ArtifactError, match=words) as caught:
        Predictor.load(crafted)
    assert "\n" not in str(caught.value) and METADATA_NAME in str(caught.value)


def test_the_flow_of_a_checked_export_is_unchanged(export_dir):
    pair = SyntheticDataset(split="test", beams=32, num_sequences=1, frames_per_sequence=2, seed=0)[0]
    flow = Predictor.load(export_dir)(pair.pc0, pair.pc1, pair.ego1_from_ego0)
    assert flow.shape == pair.pc0.shape and np.isfinite(flow).all()


@pytest.mark.parametrize("stored", ["../../victim", "/elsewhere/victim", "../.."])
def test_a_checkpoint_cannot_choose_where_export_writes(tiny_student, tmp_path, stored):
    """A checkpoint whose stored config sends ``export.dir`` outside its run folder is refused in one line, and the
    folder it named keeps its files; ``out_dir=`` exports where the user says."""
    from fastflow3d.artifact.export import ExportError

    run = tmp_path / "downloads" / "run"
    (run / "checkpoints").mkdir(parents=True)
    victim = tmp_path / "victim"
    victim.mkdir()
    (victim / "precious.txt").write_text("mine")
    base = "/remote/run/checkpoints"
    export_dir = stored if stored.startswith("/") else str(Path(base) / stored)
    cfg = {"checkpoint_dir": base, "export": {"dir": export_dir}}
    checkpoint = place_checkpoint(tiny_student, run / "checkpoints" / "x.ckpt", stored=cfg)
    with pytest.raises(ExportError, match="outside its run folder") as caught:
        export_checkpoint(checkpoint, formats=("pt2",))
    assert "\n" not in str(caught.value)
    assert (victim / "precious.txt").read_text() == "mine" and sorted(p.name for p in victim.iterdir()) == [
        "precious.txt"
    ]
    assert not (tmp_path / "downloads" / "victim").exists()
    chosen = export_checkpoint(checkpoint, tmp_path / "mine", formats=("pt2",))
    assert (chosen / "fastflow3d.pt2").is_file()


def test_a_checkpoints_own_export_dir_inside_its_run_is_kept(tiny_student, tmp_path):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    cfg = {"checkpoint_dir": "/old/place/run/checkpoints", "export": {"dir": "/old/place/run/export"}}
    checkpoint = place_checkpoint(tiny_student, run / "checkpoints" / "x.ckpt", stored=cfg)
    assert export_checkpoint(checkpoint, formats=("pt2",)) == run / "export"
