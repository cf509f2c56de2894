"""Deprecated, removed in 0.3: the last release's ``fastflow3d.voxelize``, today ``fastflow3d.network.voxelize``."""

from fastflow3d.network.voxelize import Grid, pillar_centres, pillar_ids, voxelize
from icpflow.core.deprecation import warn_moved

__all__ = ["Grid", "pillar_centres", "pillar_ids", "voxelize"]

warn_moved("fastflow3d.voxelize", "fastflow3d.network.voxelize")
