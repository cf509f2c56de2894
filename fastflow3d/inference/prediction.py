"""What a Predictor returns and raises: :class:`Prediction` (one pair's FULL flow and what lies behind it),
:class:`PredictorError` and :class:`PredictorWarning` (one line each), and the check of its input clouds
(:func:`as_points`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fastflow3d.artifact.file_format import ArtifactError
from icpflow.core.frame_pair import FramePairError, check_points


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
    """(N, 3) float32 C-contiguous and writeable (torch.from_numpy wants that) by
    ``icpflow.core.frame_pair.check_points``;
    its one-line error as a PredictorError."""
    try:
        return check_points(values, "Predictor", name)
    except FramePairError as error:
        raise PredictorError(str(error)) from None
