"""Run a trained FastFlow3D on a pair of scans: ``Predictor.load(path)`` then ``predictor(pc0, pc1)`` -> full flow.

``path`` is an export directory (``metadata.json`` plus ``fastflow3d.onnx`` and/or ``fastflow3d.pt2``, see
``fastflow3d.artifact``), one exported file (``.onnx`` runs in ONNX Runtime, ``.pt2`` is a ``torch.export`` program,
``.pt`` a TorchScript export of an older version) or a training checkpoint (``.ckpt``, run eagerly). The predictor
moves pc0 into the ego frame of t + dt with ``ego1_from_ego0``, runs the network, which gives the residual
(ego-compensated) flow, and adds the ego flow back, so the result is FULL flow in the project convention
(``pc0 + flow`` is the position at t + dt in the ego frame of t + dt). Points outside the network's grid get the ego
flow only. Without ``ego1_from_ego0`` the ego motion is estimated from the two scans' non-ground points
(``icpflow.odometry``, the teacher's step 1).

What runs before the network is the model's preprocessing block (``icpflow.preprocess.Preprocessing``, saved in
its metadata or checkpoint): the height frame, the ground and the ego-motion settings.

* Height frame: the network saw points with the ground near ``frame.ground_z`` (0: ego origin on the ground).
  ``sensor_height`` says where the scans' origin is: a number h (the origin is h m above the ground, e.g. 1.73 for
  KITTI's velodyne frame: both scans are lifted by ``ground_z + h``), ``"auto"`` (lifted so that the ground that
  ``icpflow.preprocess.estimate_ground_height`` finds below the sensor of pc0 sits at ``ground_z``), or None (the
  default: the scans should be in the model's frame; when the ground of pc0 lies more than 0.5 m from
  ``ground_z`` they are lifted as with ``"auto"`` and a :class:`PredictorWarning` says so). A common lift changes
  no flow vector; the ego motion given or returned is in the scans' own frame.
* Ground: a model trained with ground removal (``preprocessing.remove_ground``) sees only the non-ground points of
  each scan: the masks passed in (``ground0``, ``ground1``) or, without them, those of
  ``icpflow.ground.GroundSegmenter`` with the saved settings on the lifted scans; ground pc0 points get the
  ego flow.
* Refinement (opt-in, ``refine=True`` or a ``fastflow3d.refine.RefineConfig``): the teacher's ICP started from the
  network's flow per bird's-eye-view component of pc0, kept where its checks accept it (``fastflow3d.refine``).
* Plausibility: more than 85 % of pc0 called ground, or under 20 % of pc0 inside the network's grid, gives a
  one-line :class:`PredictorWarning` (a wrong frame or settings).

A bare ``.onnx`` / ``.pt2`` / ``.pt`` without its ``metadata.json`` carries none of this: it is refused unless
``preprocessing=`` says what the metadata would have said (a ``metadata.json``, its ``preprocessing`` entry, or
``{"remove_ground": false}`` to run it on every point in the synthetic frame).
"""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fastflow3d.artifact import (
    FORMATS,
    LEGACY_FORMATS,
    METADATA_NAME,
    SUFFIX_FORMATS,
    TORCHSCRIPT_WARNING,
    ArtifactError,
    SingleSampleNet,
    TorchNetwork,
    choose_format,
    listed_file,
    load_network,
    network_metadata,
    read_metadata,
    sibling_metadata,
)
from fastflow3d.contract import ContractError, InputContract, PreparedPair, read_grid, upgrade
from fastflow3d.refine import RefineConfig, refine_residual
from icpflow.entry import one_line
from icpflow.frames import FramePairError, check_points
from icpflow.geometry import residual_to_full, rigid_problem, transform_points
from icpflow.odometry import MIN_EGO_POINTS
from icpflow.preprocess import FRAME_TOLERANCE, estimate_ground_height, implausible, lift_transform


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


class PredictorWarning(UserWarning):
    """The scans were converted into the model's height frame without being told, or their preprocessing looks
    implausible (module docstring). One line."""


@dataclass(frozen=True)
class Prediction:
    """One pair's result. ``flow`` (N0, 3) float32 FULL flow; ``residual`` (N0, 3) float32 ego-compensated flow (0
    where the network did not predict); ``in_grid`` (N0,) bool: the network predicted the point (inside the grid and
    not left out as ground); ``ground0`` (N0,) bool: left out as ground (all False for a model that sees ground);
    ``ego1_from_ego0`` (4, 4) float64 used (given or estimated), in the scans' own frame; ``lift`` (m): how far both
    scans were raised into the model's height frame (0: they were in it); ``refined`` (N0,) bool: the points whose
    flow the refinement's ICP gave (None when refinement is off); ``ego_estimated``: the ego motion was estimated
    from the scans; ``ego_assumed``: none was given and the scans had too few points to estimate one
    (``MIN_EGO_POINTS``), so the identity was used (``ego_estimated`` is then False)."""

    flow: np.ndarray
    residual: np.ndarray
    in_grid: np.ndarray
    ground0: np.ndarray
    ego1_from_ego0: np.ndarray
    ego_estimated: bool
    lift: float = 0.0
    refined: np.ndarray | None = None  # (N0,) bool: flow from the refinement's ICP (None: refinement off)
    ego_assumed: bool = False  # no transform given and too few points to estimate one: the identity was used


def as_points(name: str, values) -> np.ndarray:
    """(N, 3) float32 C-contiguous and writeable (torch.from_numpy wants that) by ``icpflow.frames.check_points``;
    its one-line error as a PredictorError."""
    try:
        return check_points(values, "Predictor", name)
    except FramePairError as error:
        raise PredictorError(str(error)) from None


def checkpoint_contract(path: Path, cfg: dict, grid) -> InputContract:
    """The input contract a checkpoint's saved config stores (any version), one line naming it if unreadable."""
    try:
        return upgrade(cfg, grid=grid)
    except ContractError as error:
        raise PredictorError(f"{path}: {one_line(error)}") from None


def given_contract(given, grid) -> InputContract:
    """The input contract a user passes for a bare exported file (``Predictor.load(preprocessing=...)``): a
    ``metadata.json`` path or dict, its ``input`` / ``preprocessing`` entry, or ``{"remove_ground": ...}``; the
    model's ``grid`` (a Grid, or None when unknown) where the given form has none."""
    if isinstance(given, (str, os.PathLike)):
        try:
            given = json.loads(Path(given).read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
            raise PredictorError(f"{given}: cannot read preprocessing: {one_line(error)}") from None
    if not isinstance(given, dict):
        raise PredictorError(f"preprocessing must be a dict or a JSON file, got {type(given).__name__}")
    try:
        contract = upgrade(given)
    except ContractError as error:
        raise PredictorError(f"preprocessing: {one_line(error)}") from None
    return contract if contract.grid is not None else contract.replace(grid=grid)


class Predictor:
    """A FastFlow3D network behind the project's conventions (see the module docstring)."""

    def __init__(
        self,
        network,
        contract: InputContract,
        backend: str,
        ego_config=None,
        sensor_height=None,
        refine=None,
        metadata=None,
    ):
        """``network(pc0_compensated, pc1) -> (residual, valid)`` on float32 numpy arrays; ``contract`` what the
        network sees (``fastflow3d.contract``: the height frame, ground removal and its settings, the ego-motion
        settings, the grid); ``ego_config`` the ego-motion settings (``icpflow.teacher.config.EgoMotionConfig`` or a
        teacher config; default: the contract's); ``sensor_height``: None, ``"auto"`` or metres (module docstring);
        ``refine``: None/False (off), True (``RefineConfig()``), a ``RefineConfig`` or a dict of its fields;
        ``metadata``: the model's metadata (for those who ask: ``Predictor.metadata``)."""
        if not (sensor_height is None or sensor_height == "auto" or _is_number(sensor_height)):
            raise PredictorError(f"sensor_height={sensor_height!r} must be None, 'auto' or metres above the ground")
        self.network, self.contract, self.backend, self.metadata = network, contract, backend, metadata or {}
        #: how many more given ego motions to compare with the identity and their inverse (:meth:`check_given_ego`):
        #: a wrong convention is the same on every pair, so the first few calls are checked (0: none)
        self.ego_checks_left = 3
        self._said: set[str] = set()  # kinds of warnings given (``_warn_once``)
        self.remove_ground, self.preprocessing = contract.remove_ground, contract.preprocessing
        self.ego_config = self.preprocessing.ego_motion if ego_config is None else ego_config
        self.sensor_height = sensor_height if sensor_height in (None, "auto") else float(sensor_height)
        try:
            self.refine = RefineConfig.of(refine)
        except (TypeError, ValueError) as error:
            raise PredictorError(one_line(error)) from None
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
        sensor_height=None,
        preprocessing=None,
        refine=None,
    ) -> Predictor:
        """From an export directory, a ``.onnx``, a ``.pt2``, a legacy ``.pt`` (TorchScript) or a ``.ckpt``.

        ``backend`` picks the format of an export directory (``onnx``, ``pt2`` or, for older exports,
        ``torchscript``; default ONNX when onnxruntime is installed and the export has it). ``device`` applies to
        PyTorch formats and checkpoints; ONNX Runtime uses CUDA when its CUDA provider is installed, else the CPU.
        ``runtime`` (``onnxruntime`` or ``openvino``), ``threads`` and ``precision`` (``f32``, ``bf16`` with
        OpenVINO) run the ONNX file on the CPU as ``fastflow3d.runtime`` tunes it.
        ``sensor_height``: see the module docstring. ``preprocessing`` (a ``metadata.json`` path, a metadata dict or
        its ``preprocessing`` entry) replaces the saved one; a bare exported file without its metadata needs it.
        ``refine``: the opt-in ICP refinement (see ``__init__``).
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
            network, kind = runtime_network(file, runtime, threads, precision), runtime
        elif path.is_dir():
            metadata = read_metadata(path / METADATA_NAME)
            kind = backend or choose_format(metadata["files"], path)
            if kind not in FORMATS + LEGACY_FORMATS:
                raise PredictorError(f"{path}: unknown backend {kind!r}; use one of {', '.join(FORMATS)}")
            network = _network(listed_file(path, metadata, kind), kind, device)
        else:
            kind = "checkpoint" if path.suffix.lower() == ".ckpt" else SUFFIX_FORMATS.get(path.suffix.lower())
            if kind is None:
                raise PredictorError(f"{path}: expected an export directory, .onnx, .pt2, .pt (TorchScript) or .ckpt")
            if not path.is_file():
                raise PredictorError(f"{path}: file not found")
            if backend is not None and backend != kind:
                raise PredictorError(f"{path}: a {path.suffix} file cannot run with backend {backend!r}")
            if kind in LEGACY_FORMATS and backend is None:
                raise PredictorError(f"{path}: refused: {TORCHSCRIPT_WARNING}")
            if kind == "checkpoint":
                from fastflow3d.checkpoint import load_student

                model, cfg = load_student(path, map_location=device)
                contract = checkpoint_contract(path, cfg, model.grid)
                metadata = network_metadata(model, dict(cfg.get("model") or {}), path, contract)
                network, kind = TorchNetwork(SingleSampleNet(model).eval(), device), "eager"
            else:
                metadata = sibling_metadata(path, kind)
                network = _network(path, kind, device)
        if kind in LEGACY_FORMATS:  # asked for by name (else refused above)
            warnings.warn(f"{path}: {TORCHSCRIPT_WARNING}", UserWarning, stacklevel=2)
        if not metadata and preprocessing is None:
            raise PredictorError(
                f"{path}: no {METADATA_NAME} beside it describes this file, so its preprocessing (ground "
                "removal, height frame) is unknown and running it could silently give wrong flow; load its "
                "export directory, or pass what the metadata says: preprocessing=<metadata.json> "
                "(fastflow3d-infer --metadata FILE), or {'remove_ground': False} (--remove-ground no) to run "
                "it on every point"
            )
        if preprocessing is not None:
            grid = metadata.get("grid") if isinstance(metadata, dict) else None
            contract = given_contract(preprocessing, read_grid(grid, path) if isinstance(grid, dict) else None)
        else:
            try:
                contract = upgrade(metadata)
            except ContractError as error:
                raise PredictorError(f"{path}: metadata: {one_line(error)}") from None
        return cls(network, contract, kind, ego_config, sensor_height, refine, metadata)

    def __call__(self, pc0, pc1, ego1_from_ego0: np.ndarray | None = None, ground0=None, ground1=None) -> np.ndarray:
        """(N0, 3) float32 FULL flow of pc0 (N0, 3) towards pc1 (N1, 3), each in its own ego frame; the ego motion
        is estimated if None; ground masks (N0,) / (N1,) bool are computed if None and the model removes ground."""
        return self.predict(pc0, pc1, ego1_from_ego0, ground0, ground1).flow

    def predict(self, pc0, pc1, ego1_from_ego0: np.ndarray | None = None, ground0=None, ground1=None) -> Prediction:
        """Full flow with the residual, masks and ego motion behind it (see :class:`Prediction`)."""
        pc0, pc1 = as_points("pc0", pc0), as_points("pc1", pc1)
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
        return self.flow_in_frame(lifted, ego_frame, ground0, ground1, lift, estimated, assumed, check_ego)

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
        run_network: bool = True,
    ) -> Prediction:
        """The :class:`Prediction` of a pair already in the model's height frame: ``lifted`` (pc0, pc1) (N, 3)
        float32 raised by ``lift`` m, ``ego_frame`` (4, 4) in that frame, the ground masks (N,) bool (from
        :meth:`ground_mask`). What :meth:`predict` and a stream (``fastflow3d.stream``) run after their own ego
        motion and ground steps; ``check_ego``: compare the given ego motion with the identity and its inverse;
        ``run_network`` False: the ego flow only (a stream's pair with too few points)."""
        pair = self.contract.prepare(*lifted, ego_frame, ground0, ground1)  # already in the height frame
        if check_ego:
            self.ego_checks_left -= 1
            self.check_given_ego(pair.pc0[~pair.ground0], pair.pc1[~pair.ground1], pair.ego1_from_ego0)
        count = len(pair.pc0)
        residual, in_grid = np.zeros((count, 3), np.float32), np.zeros(count, bool)
        refined = np.zeros(count, bool) if self.refine is not None else None
        if run_network and len(pair.rows0) and len(pair.rows1):  # the network needs points in both scans
            kept, valid = self.network(pair.network0, pair.network1)
            if not np.isfinite(kept[valid]).all():
                raise PredictorError(
                    f"{self.backend} model: the network returned non-finite flow for "
                    f"{int((~np.isfinite(kept[valid])).any(axis=1).sum())} point(s) (NaN or Inf weights?); "
                    "nothing is returned"
                )
            residual, in_grid = self.contract.restore(pair, kept, valid)
            if self.refine is not None:
                rows = np.flatnonzero(in_grid)
                residual[rows], refined[rows] = refine_residual(
                    pair.compensated[rows], residual[rows], pair.pc1[~pair.ground1], self.refine
                )
        self.check_plausible(pair)
        flow = residual_to_full(residual, pair.pc0, pair.ego1_from_ego0)  # a common lift changes no flow vector
        ego = ego_frame if lift == 0 else lift_transform(ego_frame, -lift)  # in the scans' own frame
        return Prediction(flow, residual, in_grid, pair.ground0, ego, estimated, float(lift), refined, assumed)

    def frame_lift(self, pc0: np.ndarray) -> float:
        """Metres to raise both scans by so that their ground sits where the model's frame has it (module
        docstring); warns when it lifts scans it was not told about."""
        target = self.preprocessing.frame.ground_z
        if self.sensor_height not in (None, "auto"):
            return target + self.sensor_height
        ground = estimate_ground_height(pc0)
        if ground is None:
            if self.sensor_height == "auto":
                self._warn_once(
                    "no ground",
                    "Predictor: sensor_height='auto' found no ground in pc0 (too few points within 30 m); the scans "
                    "are used as they are",
                )
            return 0.0
        if self.sensor_height == "auto":
            return target - ground
        if abs(ground - target) <= FRAME_TOLERANCE:
            return 0.0
        self._warn_once(
            "lift",
            f"Predictor: the ground of pc0 lies at z = {ground:.2f} m but the model's frame has it at z = "
            f"{target:.2f} m; both scans lifted by {target - ground:+.2f} m (pass sensor_height=<metres of the "
            f"origin above the ground>, e.g. 1.73 for KITTI's velodyne frame, or 'auto' to say so: Predictor.load "
            "and eval.py sensor_height=..., fastflow3d-infer --sensor-height; said once, every pair is lifted by "
            "its own ground)",
        )
        return target - ground

    def _warn_once(self, kind: str, message: str) -> None:
        """A ``PredictorWarning`` of this ``kind`` once per Predictor (an evaluation or a stream says it once)."""
        if kind not in self._said:
            self._said.add(kind)
            warnings.warn(message, PredictorWarning, stacklevel=4)

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

    def ground_mask(self, name: str, points: np.ndarray, given) -> np.ndarray:
        """(N,) bool mask of the points the network leaves out (:meth:`scan_masks`)."""
        return self.scan_masks(name, points, given)[0]

    def scan_masks(self, name: str, points: np.ndarray, given) -> tuple[np.ndarray, np.ndarray]:
        """The (N,) bool masks of the (N, 3) scan in the model's height frame that the network and the odometry leave
        out: the ``given`` ground mask for both, or the segmentation's with the saved settings
        (``icpflow.ground.GroundSegmenter.masks``: the ground, objects kept whole, and the ground's surface). The
        network's is empty for a model that sees ground."""
        if given is not None:
            mask = np.asarray(given)
            if mask.dtype != bool or mask.shape != (len(points),):
                raise PredictorError(f"{name} must be a bool ({len(points)},) mask, got {mask.dtype} {mask.shape}")
            surface = mask
        else:
            mask, surface = self.segmenter().masks(points)
        return (mask if self.remove_ground else np.zeros(len(points), bool)), surface

    def segmenter(self):
        """The ground segmentation of the model's saved settings (``icpflow.ground.GroundSegmenter``)."""
        if self._segmenter is None:
            from icpflow.ground import GroundSegmenter

            self._segmenter = GroundSegmenter(self.preprocessing)
        return self._segmenter

    def check_given_ego(self, pc0: np.ndarray, pc1: np.ndarray, ego: np.ndarray) -> None:
        """Warn when a given ``ego`` (pc0's frame -> pc1's) fits the scans clearly worse than the identity or its
        inverse: the mean distance (clipped at 2 m) of up to 2,000 pc0 points, moved by each transform, to their
        nearest of up to 20,000 pc1 points (non-ground points when the model removes ground; about 6 ms on a KITTI
        scan, on the first ``ego_checks_left`` calls only; a warning ends the checks). An inverted transform, or
        one of another frame, makes static structure disagree by twice the ego motion."""
        from scipy.spatial import cKDTree

        if len(pc0) < MIN_EGO_POINTS or len(pc1) < MIN_EGO_POINTS:
            return
        source = pc0[:: max(1, len(pc0) // 2000)].astype(np.float64)
        tree = cKDTree(pc1[:: max(1, len(pc1) // 20000)])
        fits = {}
        for name, transform in (("given", ego), ("the identity", np.eye(4)), ("its inverse", np.linalg.inv(ego))):
            fits[name] = float(np.minimum(tree.query(transform_points(transform, source))[0], 2.0).mean())
        best = min(("the identity", "its inverse"), key=fits.get)
        if fits["given"] > 1.5 * fits[best] and fits["given"] - fits[best] > 0.05:
            self.ego_checks_left = 0
            warnings.warn(
                f"Predictor: the given ego1_from_ego0 fits the scans worse than {best} (mean distance "
                f"{fits['given']:.2f} m against {fits[best]:.2f} m): is it inverted, or of another frame? It must "
                "map pc0's ego frame into pc1's",
                PredictorWarning,
                stacklevel=3,
            )

    def estimate_ego_motion(self, pc0: np.ndarray, pc1: np.ndarray, ground0=None, ground1=None) -> np.ndarray:
        """(4, 4) float64 ``ego1_from_ego0`` from the two scans in the height frame, their (N,) bool ground masks
        left out (``icpflow.odometry``: the teacher's step 1). Raises PredictorError when no estimate fits."""
        from icpflow.odometry import estimate_ego_motion

        try:
            ego = estimate_ego_motion(pc0, pc1, self.ego_config, ground0, ground1)
        except (RuntimeError, ValueError, MemoryError) as error:
            raise PredictorError(f"ego-motion estimation failed ({type(error).__name__}: {one_line(error)})") from None
        if ego is None:
            raise PredictorError("no ego motion fits the two scans (do they overlap?); pass ego1_from_ego0")
        return ego


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value == value
