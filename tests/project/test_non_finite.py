"""Non-finite values are stopped at every door (issue 31, point 2): the labeller fails a sample whose labels are not
finite, training stops at the first non-finite loss naming the step and the samples, the export's parity check
fails on non-finite outputs, the Predictor refuses to return them (shard verification:
tests/icpflow/shards/test_shards.py)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from fastflow3d.artifact.export import ExportError, export_model
from fastflow3d.inference.prediction import PredictorError
from fastflow3d.inference.predictor import Predictor
from fastflow3d.training.run_folder import TrainError
from fastflow3d.training.trainer import fit
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.labelling import sample as labelling_sample
from icpflow.teacher.config import ICPFlowConfig
from icpflow.teacher.long_horizon import SampleFlow

from helpers.shards import write_pseudo_labels
from helpers.students import tiny_network  # tests/ is on sys.path (pytest prepend import mode)
from helpers.training import TINY_MODEL, train_cfg


@pytest.fixture(scope="module")
def pairs():
    dataset = SyntheticDataset(split="test", beams=32, num_sequences=1, frames_per_sequence=3, seed=0)
    return [dataset[0], dataset[1]]


def test_the_labeller_fails_a_sample_whose_labels_are_not_finite(pairs, monkeypatch):
    pair = pairs[0]
    flow = np.zeros((len(pair.pc0), 3), np.float32)
    flow[:5] = np.nan
    labels = SampleFlow(
        flow=flow,
        confidence=np.ones(len(pair.pc0), np.float32),
        ego1_from_ego0=np.eye(4),
        cluster=np.full(len(pair.pc0), -1, np.int32),
        ground0=np.zeros(len(pair.pc0), bool),
        ground1=np.zeros(len(pair.pc1), bool),
    )
    monkeypatch.setattr(labelling_sample, "teacher_on_sample", lambda *args: labels)
    dataset = SimpleNamespace(pair=lambda index, horizon: pair, sample_id=lambda index: "s0")
    job = SimpleNamespace(
        dataset=dataset, teacher_cfg=ICPFlowConfig.preset("waymo"), horizon=1, tracker=False, labeller=None
    )
    outcome = labelling_sample.label_sample(job, 0, 1)
    assert "sample" not in outcome
    assert outcome["failure"]["reason"] == "NonFiniteLabels: the labeller's labels are not finite: flow (15 values)"


def test_training_stops_at_the_first_non_finite_loss_naming_step_and_samples(pairs, tmp_path, monkeypatch):
    shards = write_pseudo_labels(tmp_path / "shards", pairs)
    from fastflow3d.training import student_module

    real = student_module.StudentModule.loss

    def poisoned(self, pred, valid, batch):
        loss = real(self, pred, valid, batch)
        return loss * float("nan") if self.global_step == 2 else loss

    monkeypatch.setattr(student_module.StudentModule, "loss", poisoned)
    cfg = train_cfg(
        tmp_path, shards, shards, "trainer.max_steps=5", "data.batch_size=1", "trainer.val_check_interval=5"
    )
    with pytest.raises(TrainError, match=r"non-finite training loss \(nan\) at step 2 on samples ") as caught:
        fit(cfg)
    message = str(caught.value)
    assert "\n" not in message and pairs[0].sample_id.split("/")[0] in message
    assert not list((tmp_path / "run").rglob("best-*.ckpt")), "no best checkpoint from a NaN run"


def test_the_export_parity_check_fails_on_non_finite_output(tmp_path):
    torch.manual_seed(0)
    model = tiny_network()
    with torch.no_grad():
        next(model.parameters()).fill_(float("nan"))
    with pytest.raises(ExportError, match="non-finite flow") as caught:
        export_model(model, tmp_path / "export", ("pt2",), model_config=TINY_MODEL)
    assert "\n" not in str(caught.value) and not (tmp_path / "export").exists()


def test_the_predictor_refuses_to_return_non_finite_flow(pairs, tmp_path):
    torch.manual_seed(0)
    export_model(tiny_network(), tmp_path / "export", ("pt2",), model_config=TINY_MODEL)
    predictor = Predictor.load(tmp_path / "export")
    pair = pairs[0]
    assert np.isfinite(predictor(pair.pc0, pair.pc1, pair.ego1_from_ego0)).all()
    network = predictor.network

    def poisoned(pc0, pc1):
        residual, valid = network(pc0, pc1)
        residual = residual.copy()
        residual[np.flatnonzero(valid)[:3]] = np.nan
        return residual, valid

    predictor.network = poisoned
    with pytest.raises(PredictorError, match=r"returned non-finite flow for 3 point\(s\)"):
        predictor(pair.pc0, pair.pc1, pair.ego1_from_ego0)
