"""Distillation rounds: ``label.py labeller=student`` labels with a student export (or checkpoint) and the
refinement, and its shards say which labeller and which checkpoint made them."""

import shutil

import numpy as np
import yaml

from fastflow3d.inference.predictor import Predictor
from icpflow.datasets.synthetic import SyntheticDataset
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
