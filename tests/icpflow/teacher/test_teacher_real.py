"""The ICP-Flow teacher on real LiDAR: the Argoverse 2 pair and KITTI sequence 01 frames in ../shared/data."""

from __future__ import annotations

import numpy as np
import pytest

from icpflow.core.geometry import ego_flow, pose_error, relative_transform
from icpflow.teacher import ICPFlow, ICPFlowConfig

from helpers.data import require_shared, shared

SEQ01_FRAMES = ("kitti_odometry_seq01", "kitti_odom_seq01_frames000-002_with_gt_poses.npz")


@pytest.fixture(scope="module")
def kitti():
    return np.load(require_shared(*SEQ01_FRAMES, what="the real KITTI sequence 01 frames", kind="file"))


@pytest.fixture(scope="module")
def kitti_result(kitti):
    teacher = ICPFlow(
        ICPFlowConfig.preset("waymo", ground={"method": "patchwork", "patchwork_z_offset": 0.0}, crop_xy=51.2)
    )
    pc0, pc1 = kitti["points0"].astype(np.float32), kitti["points1"].astype(np.float32)
    return teacher(pc0, pc1)  # no ego motion given: KISS-ICP (+ point-to-plane refinement)


@pytest.mark.slow
def test_kitti_ego_motion_and_static_flow(kitti, kitti_result):
    truth = relative_transform(kitti["velo_poses_world"][0], kitti["velo_poses_world"][1])
    translation, angle = pose_error(kitti_result.ego1_from_ego0, truth)
    assert translation < 0.05
    assert angle < 0.2
    pc0 = kitti["points0"].astype(np.float32)
    static = kitti["labels0"].reshape(-1) != 1  # every non-car point is static
    error = np.linalg.norm(kitti_result.flow - ego_flow(pc0, truth), axis=1)[static]
    assert error.mean() < 0.05
    assert kitti_result.ground0.mean() > 0.3  # Patchwork++ found the road


@pytest.fixture(scope="module")
def av2_pair():
    pytest.importorskip("av2", reason="the av2 package is an optional dependency")
    require_shared("av2", "sensor", "val", what="the real Argoverse 2 sample")
    from icpflow.datasets.av2 import AV2Dataset

    return AV2Dataset(shared("av2"), split="val", ground_threshold=0.4).pair(0)  # map ground: within 0.4 m


@pytest.fixture(scope="module")
def av2_result(av2_pair):
    p = av2_pair  # with the sweeps' per-point times, so the preset's de-skew step runs
    return ICPFlow(ICPFlowConfig.preset("av2"))(
        p.pc0, p.pc1, p.ego1_from_ego0, p.ground0, p.ground1, p.time0, p.time1, dt=p.dt
    )


@pytest.mark.slow
def test_av2_flow_beats_zero_flow_and_is_repeatable(av2_pair, av2_result):
    p = av2_pair
    error = np.linalg.norm(av2_result.flow - p.flow, axis=1)
    zero = np.linalg.norm(ego_flow(p.pc0, p.ego1_from_ego0) - p.flow, axis=1)
    assert zero[p.dynamic].mean() == pytest.approx(0.664, abs=0.002)  # the zero-flow baseline
    assert error[~p.dynamic].mean() < 0.03
    again = ICPFlow(ICPFlowConfig.preset("av2"))(
        p.pc0, p.pc1, p.ego1_from_ego0, p.ground0, p.ground1, p.time0, p.time1, dt=p.dt
    )
    np.testing.assert_array_equal(again.flow, av2_result.flow)  # same input, same output
    np.testing.assert_array_equal(again.confidence, av2_result.confidence)


@pytest.mark.slow
def test_av2_dynamic_epe_target(av2_pair, av2_result):
    """The issue's target, dynamic EPE <= 0.15 m, on a stricter protocol than eval.py's: every dynamic point,
    ground included (map ground within 0.4 m), no 51.2 m crop. Measured 0.107 with de-skew (0.192 without:
    one car, 920 points moving 0.82 m, registered 0.2 m short between its rolling-shutter smeared scans);
    eval.py's dynamic foreground (non-ground, crop 51.2 m) measures 0.066."""
    error = np.linalg.norm(av2_result.flow - av2_pair.flow, axis=1)
    assert error[av2_pair.dynamic].mean() <= 0.15
    assert av2_result.n_deskewed >= 1
    p = av2_pair
    plain = ICPFlow(ICPFlowConfig.preset("av2", deskew={"enabled": False}))(
        p.pc0, p.pc1, p.ego1_from_ego0, p.ground0, p.ground1
    )
    plain_error = np.linalg.norm(plain.flow - p.flow, axis=1)
    assert plain_error[p.dynamic].mean() > error[p.dynamic].mean() + 0.05  # the de-skew step is what gets there
