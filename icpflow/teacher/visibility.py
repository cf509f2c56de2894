"""Which directions a scan covered: the azimuths about its sensor's vertical axis where it has points.

A spinning LiDAR covers every azimuth; a scan cropped to a front camera's view (KITTI's scene-flow pairs) covers a
sector. Under the hypothesis that an object is static, its points that fall outside the next scan's sector could not
have been seen there, so they are no evidence against that hypothesis (``pipeline._prefer_static`` leaves them out of
the plane test). Points are (N, 3) in the scan's own frame (the height frame: the sensor on the z axis).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: azimuth bins over the full turn (0.5 degrees each: a 64-beam scan has points in every bin of its sector)
AZIMUTH_BINS = 720
#: bins (2 degrees) taken off each edge of a sector: a camera's view is cut by planes through the camera, not the
#: sensor, so near its edges the scan covers some heights and ranges of a direction and not others
EDGE_BINS = 4


def _bins(points: np.ndarray) -> np.ndarray:
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    return np.minimum(((azimuth + np.pi) / (2 * np.pi) * AZIMUTH_BINS).astype(np.int64), AZIMUTH_BINS - 1)


@dataclass(frozen=True)
class ScanView:
    """``covered`` (AZIMUTH_BINS,) bool: the azimuth bins holding points of the scan, ``EDGE_BINS`` or more from any
    bin that holds none (the turn wraps around)."""

    covered: np.ndarray

    @classmethod
    def of(cls, points: np.ndarray) -> ScanView:
        """The view of a scan's (N, 3) points (its own frame)."""
        covered = np.zeros(AZIMUTH_BINS, dtype=bool)
        covered[_bins(np.asarray(points, dtype=np.float64).reshape(-1, 3))] = True
        if covered.all():
            return cls(covered)
        edge = np.convolve(np.r_[~covered[-EDGE_BINS:], ~covered, ~covered[:EDGE_BINS]], np.ones(2 * EDGE_BINS + 1))
        return cls(covered & (edge[2 * EDGE_BINS : -2 * EDGE_BINS] == 0))

    @property
    def full(self) -> bool:
        """Every azimuth covered (a spinning sensor's whole scan)."""
        return bool(self.covered.all())

    def sees(self, points: np.ndarray) -> np.ndarray:
        """(M,) bool: which of (M, 3) points in the scan's frame lie in a covered direction."""
        return self.covered[_bins(np.asarray(points, dtype=np.float64).reshape(-1, 3))]
