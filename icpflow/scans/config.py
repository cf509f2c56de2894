"""The settings blocks of the scan steps both wings take: ``ego_motion`` (``icpflow.scans.odometry``) and ``ground``
(``icpflow.scans.ground``). The teacher's config holds them as its steps 1 and 2 (``icpflow.teacher.config``), a
student's preprocessing as its own (``icpflow.scans.preprocess.Preprocessing``)."""

from __future__ import annotations

from dataclasses import dataclass

from icpflow.core.settings import Checked, setting

#: the most cells of the ground's height map (``icpflow.scans.ground.ground_height``: (2 * patchwork_max_range /
#: cell) ** 2 of them, 4 bytes each and a few working arrays): 16.7 M, a 2 km wide map of 0.5 m cells; the defaults
#: make 65,536
MAX_HEIGHT_MAP_CELLS = 1 << 24


@dataclass(frozen=True)
class EgoMotionConfig(Checked):
    """Step 1 (``ego_motion``): ``ego1_from_ego0`` by KISS-ICP, then point-to-plane refinement
    (``teacher.ego_motion``)."""

    # "given": use the ego1_from_ego0 passed in, KISS-ICP when none is; "kiss_icp": always estimate it (the
    # ablation: a transform passed in is ignored)
    method: str = setting("given", choices=("given", "kiss_icp"), old="ego_motion")
    kiss_voxel_size: float = setting(1.0, "positive")  # KISS-ICP voxel size (m)
    kiss_max_range: float = setting(100.0, "positive")  # KISS-ICP max range (m)
    refine_voxel: float = setting(0.2, "non_negative", old="ego_refine_voxel")  # refinement voxel (m); 0 = off


@dataclass(frozen=True)
class GroundConfig(Checked):
    """Step 2 (``ground``): ground removal per scan (``icpflow.scans.ground``). ``local``: a local ground height from
    Patchwork++'s ground, objects kept whole; ``both`` (the reference, and every model stored before ``local``): a
    point is non-ground only if Patchwork++ and the z threshold both say so."""

    method: str = setting("local", choices=("local", "both", "patchwork", "zthreshold", "none"), old="ground")
    sensor_height: float = setting(1.723, "non_negative")  # Patchwork++ sensor height above the ground (m)
    patchwork_max_range: float = setting(64.0, "positive")  # Patchwork++ max_range (m); also the local map's reach
    patchwork_z_offset: float = setting(0.0, "number")  # added to z before Patchwork++ (ground near -sensor_height)
    range_z: float = setting(0.04, "number")  # z threshold: ground if z <= range_z + slack
    slack: float = setting(0.3, "non_negative", old="ground_slack")
    # local: ground if at most margin above the local ground height (m), a map of cell m cells whose lower
    # envelope rises at most slope (m per m); a ground point within column_radius (m, horizontally) of a non-ground
    # point at most column_gap above the ground (m) belongs to that object (BENCHMARKS.md, "Ground that keeps
    # moving objects")
    margin: float = setting(0.15, "non_negative")
    cell: float = setting(0.5, "positive")
    slope: float = setting(0.3, "non_negative")
    column_radius: float = setting(0.15, "non_negative")
    column_gap: float = setting(0.6, "non_negative")

    def __post_init__(self):
        super().__post_init__()
        cells = (2.0 * self.patchwork_max_range / self.cell) ** 2
        if cells > MAX_HEIGHT_MAP_CELLS:
            raise ValueError(
                f"GroundConfig: patchwork_max_range {self.patchwork_max_range:g} m in cells of {self.cell:g} m makes "
                f"a ground-height map of {cells:.3g} cells, over the {MAX_HEIGHT_MAP_CELLS} it may hold: raise "
                "ground.cell or lower ground.patchwork_max_range"
            )
