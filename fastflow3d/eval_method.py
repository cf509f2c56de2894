"""The student as an evaluation method: ``student_method(cfg)`` for ``icpflow.evaluation.run_eval``'s
``extra_methods`` (``eval.py`` adds it as ``student``), and ``refined_student_method(cfg)``, the same model with the
Predictor's ICP refinement (``fastflow3d.refine``; ``eval.py`` method ``student+refine``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fastflow3d.predictor import Predictor
from icpflow.evaluation import EvaluationError
from icpflow.frames import FramePair


class StudentMethod:
    """A trained FastFlow3D (checkpoint or export): ``method(pair, index) -> (N0, 3) float32 FULL flow``, given the
    pair's ego motion and ground masks as the teacher is (each estimated by the Predictor when the dataset has none)."""

    def __init__(self, path, refine=None, sensor_height=None):
        self.predictor = Predictor.load(path, refine=refine, sensor_height=sensor_height)

    def __call__(self, pair: FramePair, index: int) -> np.ndarray:
        return self.predictor(pair.pc0, pair.pc1, pair.ego1_from_ego0, pair.ground0, pair.ground1)


def student_method(cfg, refine=None) -> StudentMethod:
    """The student of ``cfg.checkpoint`` (a ``.ckpt``, an export directory or an exported file) with the height
    frame ``cfg.sensor_height`` (None, ``auto`` or metres); ``refine`` as ``Predictor.load`` takes it."""
    checkpoint = cfg.checkpoint
    if not checkpoint:
        raise EvaluationError("method student needs checkpoint=<.ckpt or export>")
    if not Path(checkpoint).exists():
        raise EvaluationError(f"{checkpoint}: checkpoint does not exist")
    return StudentMethod(checkpoint, refine, cfg.get("sensor_height"))


def refined_student_method(cfg) -> StudentMethod:
    """The student of ``cfg.checkpoint`` with the default ICP refinement (``fastflow3d.refine.RefineConfig()``)."""
    return student_method(cfg, refine=True)
