"""The model in the box (``fastflow3d.artifact.shipped``): its recorded contract, its card, that ``Predictor.load()``
and ``fastflow3d-infer SCANS`` run it with no model named (and say so), and how the CLI tells a model from scans."""

import json
from pathlib import Path

import numpy as np
import pytest

import icpflow
from fastflow3d.artifact.file_format import METADATA_NAME, listed_file
from fastflow3d.artifact.shipped import CARD_NAME, SHIPPED_NAME, shipped_label, shipped_model
from fastflow3d.inference.cli import main as infer_main
from fastflow3d.inference.cli import split_paths
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.evaluation.metrics import frame_pair_stats

SHIPPED = shipped_model()
METADATA = json.loads((SHIPPED / METADATA_NAME).read_text())


def dynamic_epe(pair, flow) -> float:
    """The mean EPE (m) of the pair's moving foreground points."""
    epe_sum, *_, count = frame_pair_stats(pair, flow)["dynamic_fg"]
    return epe_sum / count


@pytest.fixture(scope="module")
def test_pair():
    """A synthetic test pair (other seeds than the model's training data), with its exact flow."""
    return SyntheticDataset(split="test", num_sequences=1, frames_per_sequence=2, seed=3)[0]


def test_the_shipped_model_is_synthetic_cpus_student_with_both_networks_whole():
    model = METADATA["model"]
    assert (model["cell"], model["stage_channels"], model["decoder"], model["correlation_levels"]) == (
        0.5,
        [32, 64, 128],
        "linear",
        [1],
    )
    assert METADATA["grid"]["nx"] == METADATA["grid"]["ny"] == 128
    assert set(METADATA["files"]) == {"onnx", "onnx_int8"}
    for kind in METADATA["files"]:
        assert listed_file(SHIPPED, METADATA, kind).is_file()  # checked against the recorded sha256
    assert METADATA["package_version"] == icpflow.__version__
    assert METADATA["shipped"]["name"] == SHIPPED_NAME and "experiment=synthetic_cpu" in METADATA["shipped"]["command"]
    assert METADATA["input"]["remove_ground"] is True  # the input contract the Predictor follows
    assert "/" not in METADATA["source_checkpoint"]["path"]  # no path of the machine that built it


def test_the_card_says_how_it_was_made_what_it_scores_and_what_it_is_not():
    card = (SHIPPED / CARD_NAME).read_text()
    assert METADATA["shipped"]["commit"] in card and METADATA["source_checkpoint"]["sha256"] in card
    assert "64 synthetic test pairs" in card and "| student |" in card and "| icpflow |" in card
    assert "What it is not" in card and "synthetic world only" in card


def test_predictor_load_without_a_model_runs_the_shipped_one_and_beats_ego_only_on_movers(test_pair):
    from fastflow3d.inference.predictor import Predictor

    predictor = Predictor.load(precision="f32")
    assert predictor.model_name == shipped_label(predictor.metadata)
    assert predictor.model_name.startswith(f"the shipped {SHIPPED_NAME} student")
    prediction = predictor.predict(test_pair.pc0, test_pair.pc1, test_pair.ego1_from_ego0)
    ego_only = test_pair.ego_flow()
    student, baseline = (dynamic_epe(test_pair, flow) for flow in (prediction.flow, ego_only))
    assert student < 0.6 * baseline, (student, baseline)


def test_infer_without_a_model_names_the_shipped_one(test_pair, tmp_path, capsys):
    for name, points in (("a", test_pair.pc0), ("b", test_pair.pc1)):
        np.save(tmp_path / f"{name}.npy", points)
    out = tmp_path / "flow.npz"
    status = infer_main([str(tmp_path / "a.npy"), str(tmp_path / "b.npy"), "--out", str(out), "--no-bev"])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    assert f"infer: model: the shipped {SHIPPED_NAME} student (icpflow {icpflow.__version__}" in captured.err
    assert np.load(out)["flow"].shape == test_pair.pc0.shape


def test_the_first_path_is_a_model_only_where_it_looks_like_one(tmp_path):
    scans = tmp_path / "scans"
    scans.mkdir()
    export = tmp_path / "export"
    export.mkdir()
    (export / METADATA_NAME).write_text("{}")
    a, b = Path("a.bin"), Path("b.bin")
    assert split_paths([a, b]) == (None, a, b)  # a pair, the shipped model
    assert split_paths([scans]) == (None, scans, None)  # a stream, the shipped model
    assert split_paths([export, scans]) == (export, scans, None)  # an export and a stream
    assert split_paths([Path("m.onnx"), a]) == (Path("m.onnx"), a, None)  # a model file, even one not there yet
    assert split_paths([Path("m.ckpt"), a, b]) == (Path("m.ckpt"), a, b)
    assert split_paths([scans, a, b]) == (scans, a, b)  # three paths: the old form, the first one is the model
    with pytest.raises(ValueError, match="is a model: name the scans"):
        split_paths([export])
    with pytest.raises(ValueError, match="at most three paths"):
        split_paths([a, a, a, a])
