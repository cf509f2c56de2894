"""The student as an evaluation method: ``student_method(cfg)`` for ``icpflow.evaluation.run_eval``'s
``extra_methods`` (``eval.py`` adds it as ``student``), ``refined_student_method(cfg)``, the same model with the
Predictor's ICP refinement (``fastflow3d.inference.refine``; ``eval.py`` method ``student+refine``), and
``streamed_student_method(cfg)`` (``student-stream``): the same model fed the dataset's scans as a stream
(``fastflow3d.inference.stream.FlowStream``), nothing given: the ego motion and ground masks are the stream's own, and
``refined_streamed_student_method(cfg)`` (``student-stream+refine``): that stream with the refinement, as
``fastflow3d-infer MODEL DIR --refine`` runs it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fastflow3d.inference.predictor import Predictor
from icpflow.core.frame_pair import FramePair
from icpflow.evaluation import EvaluationError


class StudentMethod:
    """A trained FastFlow3D (checkpoint or export): ``method(pair, index) -> (N0, 3) float32 FULL flow``, given the
    pair's ego motion and ground masks as the teacher is (each estimated by the Predictor when the dataset has none)."""

    def __init__(self, path, refine=None, sensor_height=None, precision="auto"):
        self.predictor = Predictor.load(path, refine=refine, sensor_height=sensor_height, precision=precision)
        self.description = network_description(self.predictor)

    def __call__(self, pair: FramePair, index: int) -> np.ndarray:
        return self.predictor(pair.pc0, pair.pc1, pair.ego1_from_ego0, pair.ground0, pair.ground1)


class StreamedStudentMethod:
    """The student on the dataset's scans as a stream, nothing given: consecutive pairs of a sequence (a pair whose
    pc0 is the previous pair's pc1, same log) continue the stream; any other pair starts a new one. A pair the
    stream gives no flow (a lost track) gets the pairwise Predictor's, nothing given, with the stream's warning."""

    def __init__(self, path, sensor_height=None, refine=None, precision="auto"):
        from fastflow3d.inference.stream import FlowStream

        self.predictor = Predictor.load(path, refine=refine, sensor_height=sensor_height, precision=precision)
        self.description = network_description(self.predictor)
        self.stream = FlowStream(self.predictor)
        self._last: tuple[str | None, np.ndarray] | None = None  # (log, pc1) of the previous pair

    def __call__(self, pair: FramePair, index: int) -> np.ndarray:
        follows = self._last is not None and self._last[0] == pair.log_id and np.array_equal(self._last[1], pair.pc0)
        if not follows:
            self.stream.reset()
            self.stream.push(pair.pc0, source=f"{pair.sample_id} pc0")
        step = self.stream.push(pair.pc1, source=f"{pair.sample_id} pc1")
        self._last = (pair.log_id, pair.pc1)
        if step.prediction is None:
            return self.predictor(pair.pc0, pair.pc1)
        return step.prediction.flow


def network_description(predictor: Predictor) -> str:
    """What a student method runs, as ``eval.py`` prints it under its table: ``int8 network, onnxruntime``."""
    return f"{predictor.precision} network, {predictor.backend}"


def streamed_student_method(cfg) -> StreamedStudentMethod:
    """The student of ``cfg.checkpoint`` in streaming mode (``StreamedStudentMethod``)."""
    return StreamedStudentMethod(_checkpoint(cfg), cfg.get("sensor_height"), precision=_precision(cfg))


def refined_streamed_student_method(cfg) -> StreamedStudentMethod:
    """``streamed_student_method`` with the default ICP refinement (``fastflow3d.inference.refine.RefineConfig()``)."""
    return StreamedStudentMethod(_checkpoint(cfg), cfg.get("sensor_height"), refine=True, precision=_precision(cfg))


def _checkpoint(cfg) -> str:
    checkpoint = cfg.checkpoint
    if not checkpoint:
        raise EvaluationError("method student needs checkpoint=<.ckpt or export>")
    if not Path(checkpoint).exists():
        raise EvaluationError(f"{checkpoint}: checkpoint does not exist")
    return checkpoint


def _precision(cfg) -> str:
    """The student's ``precision`` (``eval.py precision=``: auto, as ``fastflow3d-infer`` runs it; f32; int8: the
    export's int8 network; bf16)."""
    return cfg.get("precision") or "auto"


def student_method(cfg, refine=None) -> StudentMethod:
    """The student of ``cfg.checkpoint`` (a ``.ckpt``, an export directory or an exported file) with the height
    frame ``cfg.sensor_height`` (None, ``auto`` or metres) and ``cfg.precision``; ``refine`` as ``Predictor.load``
    takes it."""
    return StudentMethod(_checkpoint(cfg), refine, cfg.get("sensor_height"), _precision(cfg))


def refined_student_method(cfg) -> StudentMethod:
    """The student of ``cfg.checkpoint`` with the default ICP refinement
    (``fastflow3d.inference.refine.RefineConfig()``)."""
    return student_method(cfg, refine=True)
