"""Step 2: ground removal per scan, on points in the height frame of ``icpflow.preprocess`` (ground near
z = ``frame.ground_z``).

Settings: the teacher's ``ground`` block (``icpflow.teacher.config.GroundConfig``), read from a ``Preprocessing``
or a teacher config. Methods (``ground.method``): ``patchwork`` (Patchwork++, ``pypatchworkpp``, on the scan
shifted so that the ground sits at -sensor_height), ``zthreshold`` (ground if ``z <= range_z + slack``), ``both``
(the reference: a point is non-ground only if both say so) and ``none``.
"""

from __future__ import annotations

import numpy as np

from icpflow.console import captured_output
from icpflow.preprocess import Preprocessing


class GroundSegmenter:
    """Ground masks for one configuration.

    Patchwork++ adapts its elevation and flatness thresholds to the scans it has seen (a ``patchworkpp`` object
    gives a different mask for the same scan the second time), so every scan gets a fresh object (about 20 us):
    a pair's ground then depends on that pair alone, whatever order or worker labels it.
    """

    def __init__(self, cfg):
        """``cfg``: a :class:`~icpflow.preprocess.Preprocessing` or a teacher config (``ICPFlowConfig``)."""
        self.settings = cfg if isinstance(cfg, Preprocessing) else Preprocessing.from_teacher(cfg)
        ground = self.settings.ground
        self._params = None
        if ground.method in ("both", "patchwork"):
            import pypatchworkpp

            params = pypatchworkpp.Parameters()
            params.verbose = False
            params.enable_RNR = False  # intensity-based noise removal: we pass no intensity
            params.intensity_thr = 0.0  # left uninitialised by the binding
            params.sensor_height = float(ground.sensor_height)
            params.min_range = 1.0
            params.max_range = float(ground.patchwork_max_range)
            self._params = params

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool ground mask of (N, 3) float32 points."""
        n = len(points)
        ground = np.zeros(n, dtype=bool)
        settings = self.settings.ground
        if n == 0 or settings.method == "none":
            return ground
        if settings.method in ("both", "zthreshold"):
            ground |= points[:, 2] <= settings.range_z + settings.slack
        if self._params is not None:
            ground |= self.patchwork(points)
        return ground

    def patchwork(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool Patchwork++ ground mask."""
        ground = np.zeros(len(points), dtype=bool)
        if len(points) < 10:
            return ground
        cloud = np.zeros((len(points), 4), dtype=np.float64)  # x, y, z, intensity (unused)
        cloud[:, :3] = points
        cloud[:, 2] += self.settings.patchwork_z_offset
        import pypatchworkpp

        with captured_output((1,)):  # Patchwork++'s constructor prints even when not verbose
            patchwork = pypatchworkpp.patchworkpp(self._params)
        patchwork.estimateGround(cloud)
        ground[np.asarray(patchwork.getGroundIndices(), dtype=np.int64)] = True
        return ground
