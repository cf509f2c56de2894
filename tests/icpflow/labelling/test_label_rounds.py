"""Distillation rounds: ``label.py labeller=student`` labels with a student export (or checkpoint) and the
refinement, and its shards say which labeller and which checkpoint made them."""

import shutil

import numpy as np
import yaml

from fastflow3d.inference.predictor import Predictor
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.labelling.cli import label
from icpflow.labelling.labeller import files_hash

from helpers.labelling import READER, label_cfg, read_samples


def _round(out, checkpoint, *overrides):
    return label(label_cfg(out, "labeller=student", f"labeller.checkpoint={checkpoint}", *overrides), progress=False)


def test_a_student_labels_a_round_with_the_refinement_and_the_shards_name_it(tiny_student, tmp_path, capsys):
    checkpoint = tmp_path / "round1.ckpt"
    shutil.copy(tiny_student, checkpoint)
    out = tmp_path / "labels"
    assert _round(out, checkpoint, "limit=3") == 0
    stored = yaml.safe_load((out / "config.yaml").read_text())
    labeller = stored["labeller"]
    assert labeller["name"] == "student" and labeller["checkpoint"] == str(checkpoint) and labeller["refine"]
    assert labeller["sha256"] == files_hash(checkpoint) and stored["teacher"]  # the teacher's block stays
    predictor, data = Predictor.load(checkpoint, refine=True), SyntheticDataset(**READER)
    samples = read_samples(out)
    assert len(samples) == 3
    for index, got in enumerate(samples):
        pair = data.pair(index)
        want = predictor.predict(pair.pc0, pair.pc1, pair.ego1_from_ego0, pair.ground0, pair.ground1)
        np.testing.assert_allclose(got["flow"], want.flow, atol=1e-6)
        assert want.refined is not None and want.refined.any()  # the refinement ran
        np.testing.assert_array_equal(got["ground0"], pair.ground0)
        np.testing.assert_array_equal(got["confidence"] > 0, want.in_grid | want.refined)
        assert (got["cluster"][~(want.in_grid | want.refined)] == -1).all() and got["cluster"].max() >= 0
    capsys.readouterr()
    assert _round(out, checkpoint, "limit=3") == 0  # a rerun keeps what is labelled
    assert "0 samples labelled, 3 skipped" in capsys.readouterr().out
    checkpoint.write_bytes(checkpoint.read_bytes() + b"\0")  # another checkpoint under the same name
    assert _round(out, checkpoint, "limit=3") == 2
    assert "labelled with another config" in capsys.readouterr().err


def test_the_teachers_runs_keep_their_config_and_a_bad_labeller_is_one_line(reference, tiny_student, tmp_path, capsys):
    assert "labeller" not in yaml.safe_load((reference / "config.yaml").read_text())  # the hash of earlier runs
    for overrides, words in (
        ([f"labeller.checkpoint={tmp_path / 'none.ckpt'}"], "does not exist"),
        ([f"labeller.checkpoint={tiny_student}", "horizon=2"], "labels pairs one frame apart"),
    ):
        capsys.readouterr()
        assert label(label_cfg(tmp_path / "labels", "labeller=student", *overrides), progress=False) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and "\n" not in err, err


def test_the_agreement_keeps_the_teachers_flow_where_the_student_agrees_and_the_students_elsewhere(
    tiny_student, reference, tmp_path
):
    """``labeller=agreement``: per point, the teacher's labels where the refined student lies within ``agree`` m of
    them, the student's elsewhere; ``agree`` huge gives the teacher's labels exactly."""
    out, everything = tmp_path / "agreement", tmp_path / "teacher"
    common = ("labeller=agreement", f"labeller.checkpoint={tiny_student}", "limit=2")
    assert label(label_cfg(out, *common, "labeller.agree=0.05"), progress=False) == 0
    assert label(label_cfg(everything, *common, "labeller.agree=1000"), progress=False) == 0
    assert yaml.safe_load((out / "config.yaml").read_text())["labeller"]["agree"] == 0.05
    student = Predictor.load(tiny_student, refine=True)
    taught, data = read_samples(reference), SyntheticDataset(**READER)
    mixed = 0
    for index, (got, whole) in enumerate(zip(read_samples(out), read_samples(everything))):
        for key in ("flow", "confidence", "cluster", "ground0", "ground1"):
            np.testing.assert_array_equal(whole[key], taught[index][key])  # the teacher's labels
        pair = data.pair(index)
        want = student.predict(pair.pc0, pair.pc1, pair.ego1_from_ego0, pair.ground0, pair.ground1).flow
        agree = np.linalg.norm(taught[index]["flow"] - want, axis=1) < 0.05
        np.testing.assert_array_equal(got["flow"][agree], taught[index]["flow"][agree])
        np.testing.assert_allclose(got["flow"][~agree], want[~agree], atol=1e-6)
        mixed += int(agree.any() and (~agree).any())
    assert mixed == 2
