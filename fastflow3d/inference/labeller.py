"""A student as ``label.py``'s labeller (``labeller=student``, ``conf/labeller/student.yaml``): a distillation round.

Round k + 1 trains on what round k's student gives with the refinement: ``StudentLabeller(checkpoint)`` runs the
export (or checkpoint) as the Predictor does (``fastflow3d.inference.predictor``), with the dataset's ego motion and
ground masks where it has them, and turns the prediction into a sample's labels (``SampleFlow``): full flow, the
ground masks the network used (the export's saved segmentation where the dataset has none), confidence 1 where the
network (or its refinement) gave the flow and 0 elsewhere, and cluster ids of the bird's-eye-view objects the
refinement works on (``fastflow3d.inference.refine.components``; -1 outside the network's points).
"""

from __future__ import annotations

import numpy as np

from fastflow3d.inference.predictor import Predictor
from fastflow3d.inference.refine import RefineConfig, components
from icpflow.teacher.long_horizon import SampleFlow


class StudentLabeller:
    """``StudentLabeller(checkpoint, refine=True, precision="auto", threads=None)(dataset, index, pair, horizon)``:
    the labels of one pair (t, t + 1) by the student at ``checkpoint`` (an export folder, ``.onnx``, ``.pt2`` or
    ``.ckpt``), refined unless ``refine`` is false, on at most ``threads`` threads."""

    def __init__(self, checkpoint: str, refine: bool = True, precision: str = "auto", threads: int | None = None):
        self.predictor = Predictor.load(checkpoint, threads=threads, precision=precision, refine=bool(refine))
        self.cell = RefineConfig().cell

    def __call__(self, dataset, index: int, pair, horizon: int) -> SampleFlow:
        if horizon != 1:
            raise ValueError(f"StudentLabeller: labels pairs one frame apart, got horizon {horizon}")
        predictor = self.predictor
        lifted = predictor.contract.lifted(pair.pc0, pair.pc1, predictor.frame_lift(pair.pc0))
        ground0, _ = predictor.scan_masks("ground0", lifted[0], pair.ground0)
        ground1, _ = predictor.scan_masks("ground1", lifted[1], pair.ground1)
        given0 = pair.ground0 if pair.ground0 is not None else ground0
        given1 = pair.ground1 if pair.ground1 is not None else ground1
        prediction = predictor.predict(pair.pc0, pair.pc1, pair.ego1_from_ego0, given0, given1)
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
            ground0=np.asarray(given0, bool),
            ground1=np.asarray(given1, bool),
        )
