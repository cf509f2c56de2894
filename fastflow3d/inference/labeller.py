"""A student as ``label.py``'s labeller (``conf/labeller/``): a distillation round.

Round k + 1 trains on what round k's student gives with the refinement:

- ``labeller=student`` (:class:`StudentLabeller`): the export (or checkpoint) run as the Predictor runs it
  (``fastflow3d.inference.predictor``), with the dataset's ego motion and ground masks where it has them (else the
  export's saved segmentation); confidence 1 where the network (or its refinement) gave the flow and 0 elsewhere;
  cluster ids of the bird's-eye-view objects the refinement works on (``fastflow3d.inference.refine.components``).
- ``labeller=agreement`` (:class:`AgreementLabeller`): the teacher and the student together, per point: the teacher's
  flow where the two agree within ``agree`` metres (the teacher is exact where it has the right match, and keeps
  static structure exactly static), the student's where they do not (a mover the teacher missed or mismatched).
"""

from __future__ import annotations

import numpy as np

from fastflow3d.inference.predictor import Predictor
from fastflow3d.inference.refine import RefineConfig, components
from icpflow.teacher.long_horizon import SampleFlow, teacher_on_sample


class StudentLabeller:
    """``StudentLabeller(checkpoint, refine=True, precision="auto", threads=None)(dataset, index, pair, horizon)``:
    the labels of one pair (t, t + 1) by the student at ``checkpoint`` (an export folder, ``.onnx``, ``.pt2`` or
    ``.ckpt``), refined unless ``refine`` is false, on at most ``threads`` threads. ``teacher``: the run's teacher
    config (unused here)."""

    def __init__(self, checkpoint: str, refine: bool = True, precision: str = "auto", threads=None, teacher=None):
        self.predictor = Predictor.load(checkpoint, threads=threads, precision=precision, refine=bool(refine))
        self.cell = RefineConfig().cell

    def __call__(self, dataset, index: int, pair, horizon: int) -> SampleFlow:
        _one_frame(horizon)
        predictor = self.predictor
        lifted = predictor.contract.lifted(pair.pc0, pair.pc1, predictor.frame_lift(pair.pc0))
        ground0 = pair.ground0 if pair.ground0 is not None else predictor.scan_masks("ground0", lifted[0], None)[0]
        ground1 = pair.ground1 if pair.ground1 is not None else predictor.scan_masks("ground1", lifted[1], None)[0]
        return self.labels(pair, np.asarray(ground0, bool), np.asarray(ground1, bool))

    def labels(self, pair, ground0: np.ndarray, ground1: np.ndarray) -> SampleFlow:
        """The student's labels of ``pair`` with these (N0,) / (N1,) bool ground masks."""
        prediction = self.predictor.predict(pair.pc0, pair.pc1, pair.ego1_from_ego0, ground0, ground1)
        predicted = prediction.in_grid | (prediction.refined if prediction.refined is not None else False)
        cluster = np.full(len(pair.pc0), -1, np.int32)
        if predicted.any():
            labels, _ = components(np.asarray(pair.pc0, np.float32), self.cell, predicted)
            cluster[predicted] = labels[predicted]
        return SampleFlow(
            flow=np.asarray(prediction.flow, np.float32),
            confidence=predicted.astype(np.float32),
            ego1_from_ego0=np.asarray(prediction.ego1_from_ego0, np.float64),
            cluster=cluster,
            ground0=ground0,
            ground1=ground1,
        )


class AgreementLabeller(StudentLabeller):
    """``AgreementLabeller(checkpoint, refine=True, precision="auto", agree=1.0, threads=None, teacher=cfg)``: the
    run's teacher (``teacher``: its ``ICPFlowConfig``) and the student on each pair (the student given the teacher's
    ego motion and ground masks), combined per point as the module docstring says. Cluster ids: the teacher's where
    its flow is kept, the student's objects (after the teacher's ids) elsewhere."""

    def __init__(self, checkpoint, refine=True, precision="auto", agree: float = 1.0, threads=None, teacher=None):
        from icpflow.labelling.sample import build_teacher

        if teacher is None:
            raise ValueError("AgreementLabeller: needs the run's teacher config (teacher=...)")
        super().__init__(checkpoint, refine, precision, threads)
        self.teacher, self.agree = build_teacher(teacher, threads or 1), float(agree)

    def __call__(self, dataset, index: int, pair, horizon: int) -> SampleFlow:
        _one_frame(horizon)
        taught = teacher_on_sample(self.teacher, dataset, index, pair, 1, False)
        student = self.labels(pair, taught.ground0, taught.ground1)
        kept = np.linalg.norm(taught.flow - student.flow, axis=1) < self.agree
        offset = int(taught.cluster.max(initial=-1)) + 1
        return SampleFlow(
            flow=np.where(kept[:, None], taught.flow, student.flow).astype(np.float32),
            confidence=np.where(kept, taught.confidence, student.confidence).astype(np.float32),
            ego1_from_ego0=taught.ego1_from_ego0,
            cluster=np.where(kept, taught.cluster, np.where(student.cluster >= 0, student.cluster + offset, -1)).astype(
                np.int32
            ),
            ground0=taught.ground0,
            ground1=taught.ground1,
        )


def _one_frame(horizon: int) -> None:
    if horizon != 1:
        raise ValueError(f"the student's labels are of pairs one frame apart, got horizon {horizon}")
