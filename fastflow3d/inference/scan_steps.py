"""The Predictor's steps on raw scans before its network, in the model's saved settings
(``icpflow.scans.preprocess.Preprocessing``, ``fastflow3d.inference.predictor``'s module docstring): the height frame
the scans are lifted into (:meth:`ScanSteps.frame_lift`), the ground masks the network and the odometry leave out
(:meth:`ScanSteps.scan_masks`), the ego motion (:meth:`ScanSteps.estimate_ego_motion`) and the check of a given one
(:meth:`ScanSteps.check_given_ego`); each kind of :class:`~fastflow3d.inference.prediction.PredictorWarning` said
once. A stream (``fastflow3d.inference.stream``) runs them one scan at a time."""

from __future__ import annotations

import warnings

import numpy as np

from fastflow3d.inference.prediction import PredictorError, PredictorWarning
from fastflow3d.network.contract import InputContract
from icpflow.core.errors_and_signals import one_line
from icpflow.core.geometry import transform_points
from icpflow.scans.odometry import MIN_EGO_POINTS
from icpflow.scans.preprocess import FRAME_TOLERANCE, estimate_ground_height


class ScanSteps:
    """The scan steps of a model with input ``contract`` (module docstring); the base of ``Predictor``."""

    def __init__(self, contract: InputContract, ego_config=None, sensor_height=None):
        """``ego_config``: the ego-motion settings (``icpflow.teacher.config.EgoMotionConfig`` or a teacher config;
        default: the contract's); ``sensor_height``: None, ``"auto"`` or metres (``Predictor``'s module docstring)."""
        check_sensor_height(sensor_height)
        #: how many more given ego motions to compare with the identity and their inverse (:meth:`check_given_ego`):
        #: a wrong convention is the same on every pair, so the first few calls are checked (0: none)
        self.ego_checks_left = 3
        self._said: set[str] = set()  # kinds of warnings given (``_warn_once``)
        self.remove_ground, self.preprocessing = contract.remove_ground, contract.preprocessing
        self.ego_config = self.preprocessing.ego_motion if ego_config is None else ego_config
        self.sensor_height = sensor_height if sensor_height in (None, "auto") else float(sensor_height)
        self._segmenter = None

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

    def ground_mask(self, name: str, points: np.ndarray, given) -> np.ndarray:
        """(N,) bool mask of the points the network leaves out (:meth:`scan_masks`)."""
        return self.scan_masks(name, points, given)[0]

    def scan_masks(self, name: str, points: np.ndarray, given) -> tuple[np.ndarray, np.ndarray]:
        """The (N,) bool masks of the (N, 3) scan in the model's height frame that the network and the odometry leave
        out: the ``given`` ground mask for both, or the segmentation's with the saved settings
        (``icpflow.scans.ground.GroundSegmenter.masks``: the ground, objects kept whole, and the ground's surface). The
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
        """The ground segmentation of the model's saved settings (``icpflow.scans.ground.GroundSegmenter``)."""
        if self._segmenter is None:
            from icpflow.scans.ground import GroundSegmenter

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
        left out (``icpflow.scans.odometry``: the teacher's step 1). Raises PredictorError when no estimate fits."""
        from icpflow.scans.odometry import estimate_ego_motion

        try:
            ego = estimate_ego_motion(pc0, pc1, self.ego_config, ground0, ground1)
        except (RuntimeError, ValueError, MemoryError) as error:
            raise PredictorError(f"ego-motion estimation failed ({type(error).__name__}: {one_line(error)})") from None
        if ego is None:
            raise PredictorError("no ego motion fits the two scans (do they overlap?); pass ego1_from_ego0")
        return ego


#: metres: the highest sensor a scan is lifted from (a car's roof is 1.5-2 m, a truck's or a mast's a few metres more);
#: a height beyond it is a typo or a unit mistake (millimetres), and lifts every scan out of the model's grid
MAX_SENSOR_HEIGHT = 100.0


def check_sensor_height(sensor_height) -> None:
    """Refuse a ``sensor_height`` other than None, ``"auto"`` or metres in [0, ``MAX_SENSOR_HEIGHT``] in one line
    (``Predictor.load``, ``fastflow3d-infer --sensor-height`` and ``eval.py sensor_height=`` alike)."""
    if not (sensor_height is None or sensor_height == "auto" or _is_height(sensor_height)):
        raise PredictorError(
            f"sensor_height={sensor_height!r} must be None, 'auto' or metres above the ground in [0, "
            f"{MAX_SENSOR_HEIGHT:g}]"
        )


def _is_height(value) -> bool:
    """A number of metres in [0, ``MAX_SENSOR_HEIGHT``] (not a bool)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and 0 <= value <= MAX_SENSOR_HEIGHT
