"""One way to open a file (``icpflow.core.files``): every reader the project has, handed a FIFO, a link to
``/dev/zero``, a folder or an oversized text file where it expects a file, refuses it in one line naming the path,
without hanging or reading until memory runs out. Each case runs in a child process with a time limit: a reader that
opened the FIFO would hang there."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from icpflow.core.files import NotAFile, not_a_file, read_text, regular_file

from helpers.data import REPO


def special(kind: str, path):
    """A FIFO, a link to /dev/zero or a folder at ``path``."""
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "zero":
        os.symlink("/dev/zero", path)
    else:
        path.mkdir()
    return path


KINDS = ["fifo", "zero", "folder"]
WORDS = {"fifo": "a FIFO, not a regular file", "zero": "a character device, not a regular file", "folder": "a folder"}


def run_child(code: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, capture_output=True, text=True, timeout=timeout
    )


@pytest.mark.parametrize("kind", KINDS)
def test_the_helper_refuses_what_is_not_a_regular_file(kind, tmp_path):
    path = special(kind, tmp_path / "x.json")
    with pytest.raises(NotAFile, match=f"^{path}: {WORDS[kind]}"):
        regular_file(path)
    with pytest.raises(NotAFile):
        read_text(path)
    big = tmp_path / "big.json"
    big.write_bytes(b" " * 2000)
    with pytest.raises(NotAFile, match=r"2000 bytes, more than the 1000"):
        read_text(big, limit=1000)
    (tmp_path / "real").write_text("x")
    os.symlink(tmp_path / "real", tmp_path / "link")
    assert read_text(tmp_path / "link") == "x"  # a link to a regular file is the file
    assert not_a_file(path).startswith(f"{path}: {WORDS[kind]}") and "\n" not in not_a_file(path)
    assert not_a_file(tmp_path / "real") is None and not_a_file(tmp_path / "absent") is None  # the caller's cases


#: each reader of a file handed by a user: (what, code reading the file at sys.argv[1], a name for it)
READERS = {
    "a scan (.bin)": ("from icpflow.datasets.file_formats import read_scan; read_scan(PATH)", "000000.bin"),
    "a scan (.npy)": ("from icpflow.datasets.file_formats import read_scan; read_scan(PATH)", "000000.npy"),
    "a scan (.ply)": ("from icpflow.datasets.file_formats import read_scan; read_scan(PATH)", "000000.ply"),
    "poses (text)": ("from icpflow.datasets.file_formats import read_poses; read_poses(PATH)", "poses.txt"),
    "an .npz (a trajectory, a pair)": (
        "from icpflow.datasets.file_formats import load_npz; load_npz(PATH, ('pc0',))",
        "trajectory.npz",
    ),
    "an export's metadata.json": (
        "from fastflow3d.artifact.file_format import read_metadata; read_metadata(PATH)",
        "metadata.json",
    ),
    "a manifest read as a stream's": (
        "from fastflow3d.inference.stream_folder import read_manifest; assert read_manifest(PATH) is None",
        "stream.json",
    ),
    "metrics.json": ("from icpflow.evaluation.report import read_metrics; read_metrics(PATH)", "metrics.json"),
}


@pytest.mark.parametrize("reader", sorted(READERS))
@pytest.mark.parametrize("kind", ["fifo", "zero"])
def test_every_reader_refuses_a_fifo_and_a_device_in_one_line(reader, kind, tmp_path):
    code, name = READERS[reader]
    path = special(kind, tmp_path / name)
    program = f"""
        import sys
        from pathlib import Path
        PATH = Path(sys.argv[1])
        try:
            {code}
        except ValueError as error:
            print("refused:", error)
        else:
            print("read")
    """
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(program), str(path)], cwd=REPO, capture_output=True, text=True,
        timeout=60,
    )  # fmt: skip
    out = done.stdout.strip()
    if reader.startswith("a manifest"):
        assert out == "read", done.stderr  # no manifest of ours: the stream refuses its folder (the next test)
    else:
        assert out.startswith(f"refused: {path}") and "\n" not in out, (out, done.stderr[-500:])


@pytest.mark.timeout(300)  # a reader that opened the FIFO would hang here
@pytest.mark.parametrize("kind", ["fifo", "zero"])
def test_the_infer_cli_refuses_special_files_in_every_option(kind, tmp_path, tiny_pt2_export, capsys):
    """``fastflow3d-infer``: a scan, ``--poses``, the export's ``metadata.json`` and a stream's ``stream.json`` in
    ``--out`` that are FIFOs or devices: exit 2, one line naming the file."""
    from fastflow3d.inference.cli import main as infer_main

    scans = tmp_path / "scans"
    scans.mkdir()
    rng = np.random.default_rng(0)
    for k in range(2):
        np.save(scans / f"{k}.npy", rng.uniform(-10, 10, (500, 3)).astype(np.float32))
    pair = [str(scans / "0.npy"), str(scans / "1.npy")]
    export = tmp_path / "export"
    export.mkdir()
    for item in tiny_pt2_export.iterdir():
        if item.name != "metadata.json":
            (export / item.name).symlink_to(item)
    out = tmp_path / "stream_out"
    out.mkdir()
    bad_scan, poses = special(kind, tmp_path / "bad.bin"), special(kind, tmp_path / "poses.txt")
    cases = [
        ([str(tiny_pt2_export), pair[0], str(bad_scan), "--out", str(tmp_path / "f.npz")], bad_scan),
        ([str(tiny_pt2_export), *pair, "--poses", str(poses), "--out", str(tmp_path / "g.npz")], poses),
        ([str(export), *pair, "--out", str(tmp_path / "h.npz")], special(kind, export / "metadata.json")),
        ([str(tiny_pt2_export), str(scans), "--out", str(out)], special(kind, out / "stream.json") and out),
    ]
    for args, named in cases:
        assert infer_main(args) == 2, args
        lines = capsys.readouterr().err.strip().splitlines()
        assert lines and str(named) in lines[-1] and "Traceback" not in "\n".join(lines), (args, lines[-3:])


def test_label_refuses_a_special_config_marker_in_its_out_dir(tmp_path):
    """``label.py``'s ``out_dir/config.yaml`` (the folder's claim) that is a FIFO: one line naming it, no hang."""
    out = tmp_path / "labels"
    out.mkdir()
    special("fifo", out / "config.yaml")
    done = run_child(
        f"""
        import sys
        from icpflow.labelling.cli import main
        sys.argv = ["label.py", "dataset.reader.num_sequences=1", "dataset.reader.frames_per_sequence=2",
                    "out_dir={out}", "hydra_dir={tmp_path / "hydra"}"]
        main()
        """,
        timeout=300,
    )
    assert done.returncode == 2 and f"{out / 'config.yaml'}: a FIFO, not a regular file" in done.stderr, done.stderr


@pytest.mark.timeout(300)  # a reader that opened the FIFO would hang here
@pytest.mark.parametrize("kind", ["fifo", "zero"])
def test_a_model_file_or_checkpoint_that_is_special_is_refused_by_each_reader(kind, tmp_path, tiny_pt2_export, capsys):
    """A checkpoint (``Predictor.load``, ``export.py checkpoint=``, ``train.py ckpt_path=``, ``label.py
    labeller.checkpoint=``: its hash) and an export's network file (``Predictor.load`` of the folder) that are FIFOs
    or devices: one line naming the file, within the time limit."""
    from omegaconf import OmegaConf

    from fastflow3d.artifact.export import run_export
    from fastflow3d.inference.prediction import PredictorError
    from fastflow3d.inference.predictor import Predictor
    from fastflow3d.training.run_folder import TrainError, resolve_ckpt_path
    from icpflow.labelling.labeller import identity

    checkpoint = special(kind, tmp_path / "student.ckpt")
    words = f"{checkpoint}: {WORDS[kind]}"
    with pytest.raises(PredictorError, match=f"^{words}"):
        Predictor.load(checkpoint)
    with pytest.raises(ValueError, match=f"^{words}"):
        identity({"name": "student", "_target_": "x.Y", "checkpoint": str(checkpoint)})
    with pytest.raises(TrainError, match=f"^ckpt_path={checkpoint}: {words}"):
        resolve_ckpt_path(OmegaConf.create({"ckpt_path": str(checkpoint), "checkpoint_dir": str(tmp_path)}), None)
    assert (
        run_export(OmegaConf.create({"checkpoint": str(checkpoint), "out_dir": None, "format": ["pt2"], "int8": False}))
        == 2
    )
    assert capsys.readouterr().err.strip().splitlines()[-1].startswith(f"export: {words}")
    export = tmp_path / "export"
    export.mkdir()
    for item in tiny_pt2_export.iterdir():
        if item.name != "fastflow3d.pt2":
            (export / item.name).symlink_to(item)
    network = special(kind, export / "fastflow3d.pt2")
    with pytest.raises(ValueError, match=f"^{network}: {WORDS[kind]}"):
        Predictor.load(export)
