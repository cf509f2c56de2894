"""Run a trained FastFlow3D on a pair of scans: ``Predictor.load(path)`` then ``predictor(pc0, pc1)`` -> full flow.

``path`` is an export directory (``metadata.json`` plus ``fastflow3d.onnx`` and/or ``fastflow3d.pt2``, see
``fastflow3d.artifact``), one exported file (``.onnx`` runs in ONNX Runtime, ``.pt2`` is a ``torch.export`` program,
``.pt`` a TorchScript export of an older version) or a training checkpoint (``.ckpt``, run eagerly). The predictor
moves pc0 into the ego frame of t + dt with ``ego1_from_ego0``, runs the network, which gives the residual
(ego-compensated) flow, and adds the ego flow back, so the result is FULL flow in the project convention
(``pc0 + flow`` is the position at t + dt in the ego frame of t + dt). Points outside the network's grid get the ego
flow only. Without ``ego1_from_ego0`` the ego motion is estimated from the two scans' non-ground points
(``icpflow.scans.odometry``, the teacher's step 1).

What runs before the network is the model's preprocessing block (``icpflow.scans.preprocess.Preprocessing``, saved in
its metadata or checkpoint): the height frame, the ground and the ego-motion settings.

* Height frame: the network saw points with the ground near ``frame.ground_z`` (0: ego origin on the ground).
  ``sensor_height`` says where the scans' origin is: a number h (the origin is h m above the ground, e.g. 1.73 for
  KITTI's velodyne frame: both scans are lifted by ``ground_z + h``), ``"auto"`` (lifted so that the ground that
  ``icpflow.scans.preprocess.estimate_ground_height`` finds below the sensor of pc0 sits at ``ground_z``), or None (the
  default: the scans should be in the model's frame; when the ground of pc0 lies more than 0.5 m from
  ``ground_z`` they are lifted as with ``"auto"`` and a :class:`PredictorWarning` says so). A common lift changes
  no flow vector; the ego motion given or returned is in the scans' own frame.
* Ground: a model trained with ground removal (``preprocessing.remove_ground``) sees only the non-ground points of
  each scan: the masks passed in (``ground0``, ``ground1``) or, without them, those of
  ``icpflow.scans.ground.GroundSegmenter`` with the saved settings on the lifted scans; ground pc0 points get the
  ego flow.
* Refinement (opt-in, ``refine=True`` or a ``fastflow3d.inference.refine.RefineConfig``): the teacher's ICP started from
  the network's flow per bird's-eye-view component of pc0, kept where its checks accept it
  (``fastflow3d.inference.refine``).
* Plausibility: more than 85 % of pc0 called ground, or under 20 % of pc0 inside the network's grid, gives a
  one-line :class:`PredictorWarning` (a wrong frame or settings).

A bare ``.onnx`` / ``.pt2`` / ``.pt`` without its ``metadata.json`` carries none of this: it is refused unless
``preprocessing=`` says what the metadata would have said (a ``metadata.json``, its ``preprocessing`` entry, or
``{"remove_ground": false}`` to run it on every point in the synthetic frame).
"""

from __future__ import annotations

import logging
import os
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np

from fastflow3d.artifact.file_format import LEGACY_FORMATS
from fastflow3d.artifact.safe_loading import TORCHSCRIPT_WARNING
from fastflow3d.artifact.shipped import shipped_label, shipped_model
from fastflow3d.inference.model_loading import AUTO, check_load_options, model_contract, open_model, precision_cost
from fastflow3d.inference.prediction import Prediction, PredictorError, PredictorWarning, as_points
from fastflow3d.inference.refine import RefineConfig, refine_residual
from fastflow3d.inference.scan_steps import ScanSteps
from fastflow3d.network.contract import InputContract, PreparedPair
from icpflow.core.errors_and_signals import one_line
from icpflow.core.geometry import residual_to_full, rigid_problem
from icpflow.scans.odometry import MIN_EGO_POINTS
from icpflow.scans.preprocess import implausible, lift_transform
from icpflow.teacher.warmup import prepare_kernels

log = logging.getLogger(__package__)


class PairResidual(NamedTuple):
    """A pair's ego-compensated flow before it is made FULL (:meth:`Predictor.pair_residual`): ``residual`` (N0, 3)
    float32 (0 where the network did not predict), ``in_grid`` (N0,) bool, ``refined`` (N0,) bool or None (as
    :class:`~fastflow3d.inference.prediction.Prediction`'s)."""

    residual: np.ndarray
    in_grid: np.ndarray
    refined: np.ndarray | None


def scans_frame_ego(ego_frame: np.ndarray, lift: float) -> np.ndarray:
    """(4, 4) ``ego1_from_ego0`` in the scans' own frame, from the same motion in the height frame (scans raised by
    ``lift`` m): what a :class:`Prediction` returns and a stream's trajectory chains."""
    return ego_frame if lift == 0 else lift_transform(ego_frame, -lift)


class Predictor(ScanSteps):
    """A FastFlow3D network behind the project's conventions (see the module docstring); the steps on raw scans
    before the network (height frame, ground masks, ego motion) are those of its base, ``ScanSteps``."""

    def __init__(
        self,
        network,
        contract: InputContract,
        backend: str,
        ego_config=None,
        sensor_height=None,
        refine=None,
        metadata=None,
        precision: str = "f32",
    ):
        """``network(pc0_compensated, pc1) -> (residual, valid)`` on float32 numpy arrays; ``contract`` what the
        network sees (``fastflow3d.network.contract``: the height frame, ground removal and its settings, the ego-motion
        settings, the grid); ``ego_config`` the ego-motion settings (``icpflow.teacher.config.EgoMotionConfig`` or a
        teacher config; default: the contract's); ``sensor_height``: None, ``"auto"`` or metres (module docstring);
        ``refine``: None/False (off), True (``RefineConfig()``), a ``RefineConfig`` or a dict of its fields;
        ``metadata``: the model's metadata (for those who ask: ``Predictor.metadata``); ``precision``: the one the
        network runs in (``f32``, ``bf16``, ``int8``; ``Predictor.precision``)."""
        super().__init__(contract, ego_config, sensor_height)  # the scan steps (ScanSteps)
        self.network, self.contract, self.backend, self.metadata = network, contract, backend, metadata or {}
        self.precision = precision
        self.model_name = "a network given in memory"  # Predictor.load names the model file (or the shipped model)
        try:
            self.refine = RefineConfig.of(refine)
        except (TypeError, ValueError) as error:
            raise PredictorError(one_line(error)) from None

    @classmethod
    def load(
        cls,
        path: str | os.PathLike | None = None,
        backend: str | None = None,
        device: str = "cpu",
        ego_config=None,
        runtime: str | None = None,
        threads: int | None = None,
        precision: str = AUTO,
        sensor_height=None,
        preprocessing=None,
        refine=None,
    ) -> Predictor:
        """From an export directory, a ``.onnx``, a ``.pt2``, a legacy ``.pt`` (TorchScript) or a ``.ckpt``; without
        ``path``, the model that ships with the package (``fastflow3d.artifact.shipped``), named in a log line and in
        ``Predictor.model_name``.

        ``backend`` picks the format of an export directory (``onnx``, ``pt2`` or, for older exports,
        ``torchscript``; default ONNX when onnxruntime is installed and the export has it). ``device`` applies to
        PyTorch formats and checkpoints; ONNX Runtime uses CUDA when its CUDA provider is installed, else the CPU.
        ``runtime`` (``onnxruntime`` or ``openvino``), ``threads`` and ``precision`` (``auto``, the default, as the
        CLI's and ``eval.py``'s: int8 where the export ships it and this CPU runs it quicker, else f32,
        ``fastflow3d.inference.model_loading.auto_precision``; ``f32``; ``bf16`` with OpenVINO; ``int8``: the export's
        int8 network in ONNX Runtime; anything else is refused) run the ONNX file on the CPU as
        ``fastflow3d.artifact.engines`` tunes it; what ran is ``Predictor.precision``.
        ``sensor_height``: see the module docstring. ``preprocessing`` (a ``metadata.json`` path, a metadata dict or
        its ``preprocessing`` entry) replaces the saved one; a bare exported file without its metadata needs it.
        ``refine``: the opt-in ICP refinement (see ``__init__``).
        Raises :class:`ArtifactError` (one line) for a path that is not a readable artifact, and its subclass
        ``PredictorError`` for an option that ``fastflow3d-infer`` and ``eval.py`` refuse too (precision, sensor height,
        threads, device, runtime: ``fastflow3d.inference.model_loading.check_load_options``).
        """
        check_load_options(precision, sensor_height, threads, device, runtime)  # before the model is opened
        path = shipped_model() if path is None else Path(path)
        asked = precision
        network, kind, metadata, precision = open_model(path, backend, device, runtime, threads, precision)
        cost = precision_cost(precision) if asked != AUTO else None
        if cost:
            warnings.warn(f"Predictor: {cost}", PredictorWarning, stacklevel=2)
        if kind in LEGACY_FORMATS:  # asked for by name (else refused by open_model)
            warnings.warn(f"{path}: {TORCHSCRIPT_WARNING}", UserWarning, stacklevel=2)
        contract = model_contract(path, metadata, preprocessing)
        predictor = cls(network, contract, kind, ego_config, sensor_height, refine, metadata, precision)
        shipped = shipped_label(metadata)
        predictor.model_name = shipped or str(path)
        if shipped:
            log.info("Predictor: %s", shipped)
        return predictor

    def __call__(self, pc0, pc1, ego1_from_ego0: np.ndarray | None = None, ground0=None, ground1=None) -> np.ndarray:
        """(N0, 3) float32 FULL flow of pc0 (N0, 3) towards pc1 (N1, 3), each in its own ego frame; the ego motion
        is estimated if None; ground masks (N0,) / (N1,) bool are computed if None and the model removes ground."""
        return self.predict(pc0, pc1, ego1_from_ego0, ground0, ground1).flow

    def predict(self, pc0, pc1, ego1_from_ego0: np.ndarray | None = None, ground0=None, ground1=None) -> Prediction:
        """Full flow with the residual, masks and ego motion behind it (see :class:`Prediction`)."""
        pc0, pc1 = as_points("pc0", pc0), as_points("pc1", pc1)
        self.prepare_kernels()
        lift = self.frame_lift(pc0)
        lifted = self.contract.lifted(pc0, pc1, lift)  # the scans in the height frame, lifted once
        estimated, assumed = ego1_from_ego0 is None, False
        if estimated and min(len(pc0), len(pc1)) < MIN_EGO_POINTS:
            warnings.warn(
                f"Predictor: too few points to estimate the ego motion (pc0 {len(pc0)}, pc1 {len(pc1)}; at least "
                f"{MIN_EGO_POINTS} each): the identity is assumed (Prediction.ego_assumed)",
                PredictorWarning,
                stacklevel=2,
            )
            ego_frame, estimated, assumed = np.eye(4), False, True
        (ground0, surface0), (ground1, surface1) = (
            self.scan_masks("ground0", lifted[0], ground0),
            self.scan_masks("ground1", lifted[1], ground1),
        )
        if estimated:
            ego_frame = self.estimate_ego_motion(*lifted, surface0, surface1)
        elif not assumed:
            ego_frame = lift_transform(np.asarray(ego1_from_ego0, dtype=np.float64), lift)
        problem = rigid_problem(ego_frame)
        if problem:
            raise PredictorError(f"{'estimated ' if estimated else ''}ego1_from_ego0 {problem}")
        check_ego = ego1_from_ego0 is not None and self.ego_checks_left > 0
        surfaces = (surface0, surface1)
        return self.flow_in_frame(lifted, ego_frame, ground0, ground1, lift, estimated, assumed, check_ego, surfaces)

    @staticmethod
    def prepare_kernels() -> None:
        """The kernels' once-per-process step (``icpflow.teacher.warmup.prepare_kernels``): its ground, odometry and
        refinement kernels never run from a cache of other sources (one line on stderr where one is emptied); each
        compiles on its first call. :meth:`predict` and a stream's first scan call it; a caller may call it first."""
        prepare_kernels("fastflow3d")

    def flow_in_frame(
        self,
        lifted: tuple[np.ndarray, np.ndarray],
        ego_frame: np.ndarray,
        ground0: np.ndarray,
        ground1: np.ndarray,
        lift: float,
        estimated: bool,
        assumed: bool = False,
        check_ego: bool = False,
        surfaces: tuple[np.ndarray, np.ndarray] | None = None,
        run_network: bool = True,
    ) -> Prediction:
        """The :class:`Prediction` of a pair already in the model's height frame: ``lifted`` (pc0, pc1) (N, 3)
        float32 raised by ``lift`` m, ``ego_frame`` (4, 4) in that frame, the ground masks (N,) bool (from
        :meth:`ground_mask`). What :meth:`predict` and a stream (``fastflow3d.inference.stream``) run after their own
        ego motion and ground steps; ``check_ego``: compare the given ego motion with the identity and its inverse;
        ``surfaces``: each scan's (N,) bool ground surface (:meth:`scan_masks`): the refinement's objects lie above it;
        ``run_network`` False: the ego flow only (a stream's pair with too few points). Its parts,
        :meth:`network_input`, :meth:`pair_residual` (the network and the refinement) and :meth:`finish`, are also
        called apart (a stream runs the network and refinement of one pair while it prepares the next scan)."""
        pair = self.network_input(lifted, ego_frame, ground0, ground1, check_ego)
        residual = self.pair_residual(pair, surfaces, run_network)
        return self.finish(pair, residual, ego_frame, lift, estimated, assumed)

    def network_input(
        self,
        lifted: tuple[np.ndarray, np.ndarray],
        ego_frame: np.ndarray,
        ground0: np.ndarray,
        ground1: np.ndarray,
        check_ego: bool = False,
    ) -> PreparedPair:
        """The pair as the network takes it (``InputContract.prepare``: the scans already in the height frame)."""
        pair = self.contract.prepare(*lifted, ego_frame, ground0, ground1)
        if check_ego:
            self.ego_checks_left -= 1
            self.check_given_ego(pair.pc0[~pair.ground0], pair.pc1[~pair.ground1], pair.ego1_from_ego0)
        return pair

    def run_network(self, pair: PreparedPair) -> tuple[np.ndarray, np.ndarray] | None:
        """The network's (residual (K0, 3), valid (K0,)) on the pair's input rows; None when a scan has no point
        for it. Touches nothing else: safe to run in another thread while this Predictor works on other scans."""
        if not (len(pair.rows0) and len(pair.rows1)):
            return None
        return self.network(pair.network0, pair.network1)

    def pair_residual(
        self,
        pair: PreparedPair,
        surfaces: tuple[np.ndarray, np.ndarray] | None = None,
        run_network: bool = True,
    ) -> PairResidual:
        """The network's residual on pc0's rows, refined when the Predictor refines (``surfaces``: the two scans'
        (N,) bool ground surface masks, :meth:`scan_masks`, under the refinement's objects); ``run_network`` False: none
        (the ego flow only). Raises PredictorError for a non-finite network output. Warns about nothing and touches
        nothing of the Predictor: a stream runs it in its worker thread (numba's threads are that thread's own)."""
        count = len(pair.pc0)
        residual, in_grid = np.zeros((count, 3), np.float32), np.zeros(count, bool)
        refined = np.zeros(count, bool) if self.refine is not None else None
        output = self.run_network(pair) if run_network else None
        if output is not None:
            kept, valid = output
            if not np.isfinite(kept[valid]).all():
                raise PredictorError(
                    f"{self.backend} model: the network returned non-finite flow for "
                    f"{int((~np.isfinite(kept[valid])).any(axis=1).sum())} point(s) (NaN or Inf weights?); "
                    "nothing is returned"
                )
            residual, in_grid = self.contract.restore(pair, kept, valid)
            if self.refine is not None:
                rows, targets = np.flatnonzero(in_grid), ~pair.ground1
                surface0, surface1 = (None, None) if surfaces is None else (surfaces[0][rows], surfaces[1][targets])
                residual[rows], refined[rows] = refine_residual(
                    pair.compensated[rows], residual[rows], pair.pc1[targets], self.refine, surface0, surface1
                )
        return PairResidual(residual, in_grid, refined)

    def finish(
        self,
        pair: PreparedPair,
        residual: PairResidual,
        ego_frame: np.ndarray,
        lift: float,
        estimated: bool,
        assumed: bool = False,
    ) -> Prediction:
        """The :class:`Prediction` from the pair's ``residual`` (:meth:`pair_residual`): checked (one warning for an
        implausible preprocessing) and made FULL flow."""
        self.check_plausible(pair)
        flow = residual_to_full(residual.residual, pair.pc0, pair.ego1_from_ego0)  # a common lift changes no flow
        ego = scans_frame_ego(ego_frame, lift)
        return Prediction(
            flow,
            residual.residual,
            residual.in_grid,
            pair.ground0,
            ego,
            estimated,
            float(lift),
            residual.refined,
            assumed,
        )

    def check_plausible(self, pair: PreparedPair) -> None:
        """One-line warning when pc0's ground fraction or its share inside the network's grid is implausible."""
        if self.contract.grid is None or not len(pair.pc0):
            return
        ground0, inside = pair.ground0, pair.inside0
        reason = implausible(float(ground0.mean()), float(inside.mean()))
        if reason:
            self._warn_once(
                "implausible",
                f"Predictor: implausible preprocessing of pc0: {reason}; is the height frame right "
                "(sensor_height=...) and are the scans in metres? (said once)",
            )
