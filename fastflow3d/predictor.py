"""Run a trained FastFlow3D on a pair of scans: ``Predictor.load(path)`` then ``predictor(pc0, pc1)`` -> full flow.

``path`` is an export directory (``metadata.json`` plus ``fastflow3d.onnx`` and/or ``fastflow3d.pt2``, see
``fastflow3d.artifact``), one exported file (``.onnx`` runs in ONNX Runtime, ``.pt2`` is a ``torch.export`` program,
``.pt`` a TorchScript export of an older version) or a training checkpoint (``.ckpt``, run eagerly). The predictor
moves pc0 into the ego frame of t + dt with ``ego1_from_ego0``, runs the network, which gives the residual
(ego-compensated) flow, and adds the ego flow back, so the result is FULL flow in the project convention
(``pc0 + flow`` is the position at t + dt in the ego frame of t + dt). Points outside the network's grid get the ego
flow only. Without ``ego1_from_ego0`` the ego motion is estimated from the
two scans with the teacher's step (KISS-ICP, then point-to-plane refinement; ``icpflow.teacher.ego_motion``).

A model trained with ground removal (``preprocessing.remove_ground`` in its metadata, ``data.remove_ground`` in its
checkpoint's config) sees only the non-ground points of each scan: the masks passed in (``ground0``, ``ground1``) or,
without them, those of ``icpflow.teacher.ground.GroundSegmenter`` on the raw scans with the teacher settings saved
with the model; ground pc0 points get the ego flow. The teacher settings saved with the model (or ``ICPFlowConfig()``
for a model without them) also drive the ego-motion estimate. A bare ``.onnx`` / ``.pt2`` / ``.pt`` without its
``metadata.json`` carries none of this: it is run on every point.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fastflow3d.artifact import (
    FORMATS,
    LEGACY_FORMATS,
    METADATA_NAME,
    SUFFIX_FORMATS,
    ArtifactError,
    SingleSampleNet,
    TorchNetwork,
    choose_format,
    listed_file,
    load_network,
    network_metadata,
    preprocessing_metadata,
    read_metadata,
    sibling_metadata,
)
from fastflow3d.model import compensate
from icpflow.frames import FramePairError, check_points
from icpflow.geometry import residual_to_full, rigid_problem


def _network(file: Path, kind: str, device: str):
    """``load_network``, except that ONNX on a machine without ONNX Runtime's CUDA provider runs with the tuned CPU
    session of ``fastflow3d.runtime`` (same numbers, 1.3 to 1.4x faster on 2 cores; BENCHMARKS.md)."""
    if kind == "onnx":
        from fastflow3d.runtime import cpu_only, runtime_network

        if cpu_only():
            return runtime_network(file, "onnxruntime")
    return load_network(file, kind, device)


class PredictorError(ArtifactError):
    """A model that cannot be used or inputs that cannot be used. The message is one line and names the cause."""


@dataclass(frozen=True)
class Prediction:
    """One pair's result. ``flow`` (N0, 3) float32 FULL flow; ``residual`` (N0, 3) float32 ego-compensated flow (0
    where the network did not predict); ``in_grid`` (N0,) bool: the network predicted the point (inside the grid and
    not left out as ground); ``ground0`` (N0,) bool: left out as ground (all False for a model that sees ground);
    ``ego1_from_ego0`` (4, 4) float64 used (given or estimated)."""

    flow: np.ndarray
    residual: np.ndarray
    in_grid: np.ndarray
    ground0: np.ndarray
    ego1_from_ego0: np.ndarray
    ego_estimated: bool


def as_points(name: str, values) -> np.ndarray:
    """(N, 3) float32 C-contiguous and writeable (torch.from_numpy wants that) by ``icpflow.frames.check_points``;
    its one-line error as a PredictorError."""
    try:
        return check_points(values, "Predictor", name)
    except FramePairError as error:
        raise PredictorError(str(error)) from None


class Predictor:
    """A FastFlow3D network behind the project's conventions (see the module docstring)."""

    def __init__(self, network, metadata: dict, backend: str, ego_config=None):
        """``network(pc0_compensated, pc1) -> (residual, valid)`` on float32 numpy arrays; ``metadata`` as an export
        writes it (its ``preprocessing`` says whether to remove ground and with which teacher settings);
        ``ego_config`` an ICPFlowConfig for the ego motion (``kiss_voxel_size``, ``kiss_max_range``,
        ``ego_refine_voxel``; default: the teacher settings saved with the model)."""
        from icpflow.teacher.config import ICPFlowConfig

        self.network, self.metadata, self.backend = network, metadata, backend
        preprocessing = metadata.get("preprocessing") or {}
        self.remove_ground = bool(preprocessing.get("remove_ground", False))
        try:
            self.teacher = ICPFlowConfig(**(preprocessing.get("teacher") or {}))
        except (TypeError, ValueError) as error:
            raise PredictorError(
                f"model metadata: preprocessing.teacher is not a set of ICPFlowConfig fields "
                f"({' '.join(str(error).split())})"
            ) from None
        self.ego_config = self.teacher if ego_config is None else ego_config
        self._segmenter = None

    @classmethod
    def load(
        cls,
        path: str | os.PathLike,
        backend: str | None = None,
        device: str = "cpu",
        ego_config=None,
        runtime: str | None = None,
        threads: int | None = None,
        precision: str = "f32",
    ) -> Predictor:
        """From an export directory, a ``.onnx``, a ``.pt2``, a legacy ``.pt`` (TorchScript) or a ``.ckpt``.

        ``backend`` picks the format of an export directory (``onnx``, ``pt2`` or, for older exports,
        ``torchscript``; default ONNX when onnxruntime is installed and the export has it). ``device`` applies to
        PyTorch formats and checkpoints; ONNX Runtime uses CUDA when its CUDA provider is installed, else the CPU.
        ``runtime`` (``onnxruntime`` or ``openvino``), ``threads`` and ``precision`` (``f32``, ``bf16`` with
        OpenVINO) run the ONNX file on the CPU as ``fastflow3d.runtime`` tunes it.
        Raises :class:`ArtifactError` (one line) for a path that is not a readable artifact.
        """
        path = Path(path)
        if runtime is not None:
            from fastflow3d.runtime import runtime_network

            if path.is_dir():
                metadata = read_metadata(path / METADATA_NAME)
                file = listed_file(path, metadata, "onnx")
            elif path.suffix.lower() == ".onnx" and path.is_file():
                file, metadata = path, sibling_metadata(path, "onnx")
            else:
                raise PredictorError(f"{path}: runtime {runtime!r} needs an export directory with ONNX or a .onnx")
            return cls(runtime_network(file, runtime, threads, precision), metadata, runtime, ego_config)
        if path.is_dir():
            metadata = read_metadata(path / METADATA_NAME)
            kind = backend or choose_format(metadata["files"])
            if kind not in FORMATS + LEGACY_FORMATS:
                raise PredictorError(f"{path}: unknown backend {kind!r}; use one of {', '.join(FORMATS)}")
            file = listed_file(path, metadata, kind)
            return cls(_network(file, kind, device), metadata, kind, ego_config)
        kind = "checkpoint" if path.suffix.lower() == ".ckpt" else SUFFIX_FORMATS.get(path.suffix.lower())
        if kind is None:
            raise PredictorError(f"{path}: expected an export directory, .onnx, .pt2, .pt (TorchScript) or .ckpt")
        if not path.is_file():
            raise PredictorError(f"{path}: file not found")
        if backend is not None and backend != kind:
            raise PredictorError(f"{path}: a {path.suffix} file cannot run with backend {backend!r}")
        if kind == "checkpoint":
            from fastflow3d.checkpoint import load_student

            model, cfg = load_student(path, map_location=device)
            metadata = network_metadata(model, dict(cfg.get("model") or {}), path, preprocessing_metadata(cfg))
            return cls(TorchNetwork(SingleSampleNet(model).eval(), device), metadata, "eager", ego_config)
        return cls(_network(path, kind, device), sibling_metadata(path, kind), kind, ego_config)

    def __call__(self, pc0, pc1, ego1_from_ego0: np.ndarray | None = None, ground0=None, ground1=None) -> np.ndarray:
        """(N0, 3) float32 FULL flow of pc0 (N0, 3) towards pc1 (N1, 3), each in its own ego frame; the ego motion
        is estimated if None; ground masks (N0,) / (N1,) bool are computed if None and the model removes ground."""
        return self.predict(pc0, pc1, ego1_from_ego0, ground0, ground1).flow

    def predict(self, pc0, pc1, ego1_from_ego0: np.ndarray | None = None, ground0=None, ground1=None) -> Prediction:
        """Full flow with the residual, masks and ego motion behind it (see :class:`Prediction`)."""
        pc0, pc1 = as_points("pc0", pc0), as_points("pc1", pc1)
        estimated = ego1_from_ego0 is None
        ego = self.estimate_ego_motion(pc0, pc1) if estimated else np.asarray(ego1_from_ego0, dtype=np.float64)
        problem = rigid_problem(ego)
        if problem:
            raise PredictorError(f"{'estimated ' if estimated else ''}ego1_from_ego0 {problem}")
        ground0, ground1 = self.ground_mask("ground0", pc0, ground0), self.ground_mask("ground1", pc1, ground1)
        residual, in_grid = np.zeros((len(pc0), 3), np.float32), np.zeros(len(pc0), bool)
        keep0, keep1 = ~ground0, ~ground1
        if keep0.any() and keep1.any():  # the network needs points in both scans
            kept, valid = self.network(compensate(pc0[keep0], ego), pc1[keep1])
            in_grid[keep0] = valid
            residual[keep0] = np.where(valid[:, None], kept, 0.0)
        return Prediction(residual_to_full(residual, pc0, ego), residual, in_grid, ground0, ego, estimated)

    def ground_mask(self, name: str, points: np.ndarray, given) -> np.ndarray:
        """(N,) bool mask of the points the network leaves out: none unless the model removes ground; then the
        given mask, or the teacher's ground segmentation of the raw (N, 3) scan."""
        if not self.remove_ground:
            return np.zeros(len(points), bool)
        if given is None:
            if self._segmenter is None:
                from icpflow.teacher.ground import GroundSegmenter

                self._segmenter = GroundSegmenter(self.teacher)
            return self._segmenter(points)
        mask = np.asarray(given)
        if mask.dtype != bool or mask.shape != (len(points),):
            raise PredictorError(f"{name} must be a bool ({len(points)},) mask, got {mask.dtype} {mask.shape}")
        return mask

    def estimate_ego_motion(self, pc0: np.ndarray, pc1: np.ndarray) -> np.ndarray:
        """(4, 4) float64 ``ego1_from_ego0`` from the two scans (KISS-ICP + refinement, the teacher's step 1)."""
        from icpflow.teacher.ego_motion import estimate_ego_motion

        try:
            return estimate_ego_motion(pc0, pc1, self.ego_config)
        except (RuntimeError, ValueError, MemoryError) as error:
            raise PredictorError(
                f"ego-motion estimation failed ({type(error).__name__}: {' '.join(str(error).split())})"
            ) from None
