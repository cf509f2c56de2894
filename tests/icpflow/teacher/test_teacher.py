"""The ICP-Flow teacher pipeline on hand-built scenes (boxes on a ground plane moved by known rigid motions)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from icpflow.core.geometry import ego_flow, make_transform
from icpflow.scans.ground import GroundSegmenter
from icpflow.teacher import ICPFlow, ICPFlowConfig
from icpflow.teacher.clustering import cluster_points, relabel_by_size, voxel_downsample
from icpflow.teacher.config import from_hydra
from icpflow.teacher.flow import match_confidence
from icpflow.teacher.long_horizon import long_horizon_flow
from icpflow.teacher.pairing import cluster_stats, plausible

from helpers.data import REPO
from helpers.teacher_scenes import scene  # tests/ is on sys.path (pytest prepend import mode)

EGO = make_transform(yaw=0.02, translation=(0.8, 0.1, 0.0))
CFG = ICPFlowConfig.preset(
    "waymo", ground={"method": "zthreshold", "range_z": 0.0, "slack": 0.1}, ego_motion={"method": "given"}
)


@pytest.fixture(scope="module")
def teacher():
    return ICPFlow(CFG)


@pytest.fixture(scope="module")
def moving_scene():
    return scene(EGO)


@pytest.fixture(scope="module")
def result(teacher, moving_scene):
    s = moving_scene
    return teacher(s["pc0"], s["pc1"], s["ego"])


# ----------------------------------------------------------------------------------------------- config


def test_presets_round_trip_and_take_block_overrides():
    """Rules every preset keeps (their numbers are test_teacher_config's previous-release check): the pairing window
    grows with the frame gap, a block override changes that field only, a config rebuilds from its dict."""
    waymo = ICPFlowConfig.preset("waymo")
    assert waymo.pairing.window(5.0, k=2) > waymo.pairing.window(0.5, k=1) > 0
    for name in ("av2", "waymo", "nuscenes"):
        preset = ICPFlowConfig.preset(name)
        changed = ICPFlowConfig.preset(name, histogram={"init": "centroid"})
        assert changed.histogram.init == "centroid" and changed.replace(histogram=preset.histogram) == preset
        assert ICPFlowConfig(**preset.to_dict()) == preset


@pytest.mark.parametrize(
    "overrides, words",
    [
        ({"ground.method": "x"}, "method must be one of .*, got .x."),
        ({"clustering": {"min_cluster_size": 0}}, "min_cluster_size"),
        ({"histogram.nms_kernel": 10}, "odd"),
        ({"checks": {"max_error": -1.0}}, "max_error"),
        ({"bogus": 1}, "unknown field"),
    ],
)
def test_config_validation_is_one_line(overrides, words):
    with pytest.raises(ValueError, match=words) as info:
        ICPFlowConfig.preset("av2").replace(**overrides)
    assert "\n" not in str(info.value)


def test_unknown_preset():
    with pytest.raises(ValueError, match="unknown preset"):
        ICPFlowConfig.preset("kitti360")


def test_hydra_group_null_means_preset():
    from hydra import compose, initialize_config_dir

    conf = REPO / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base=None):
        node = compose(
            config_name=None, overrides=["+dataset=waymo", "+icpflow=default", "icpflow.histogram.init=centroid"]
        )
        cfg = from_hydra(node.icpflow)
        assert cfg == ICPFlowConfig.preset("waymo", histogram={"init": "centroid"})
        pinned = compose(config_name=None, overrides=["+dataset=waymo", "+icpflow=nuscenes"])
        assert from_hydra(pinned.icpflow) == ICPFlowConfig.preset("nuscenes")


def test_lazy_export_keeps_import_light():
    code = (
        "import sys, icpflow; assert 'icpflow.teacher' not in sys.modules; "
        "from icpflow import ICPFlow, ICPFlowConfig; print(ICPFlow.__name__)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ICPFlow"


# ----------------------------------------------------------------------------------------------- steps


def test_ground_zthreshold_and_none():
    points = np.array([[0, 0, 0.05], [0, 0, 0.1], [0, 0, 0.11], [5, 5, 2.0]], np.float32)
    assert GroundSegmenter(CFG)(points).tolist() == [True, True, False, False]
    assert not GroundSegmenter(CFG.replace(**{"ground.method": "none"}))(points).any()


@pytest.mark.parametrize(
    "cfg, ground_z",
    [
        (ICPFlowConfig(ground={"method": "patchwork"}), -1.723),  # sensor frame: the ground 1.723 m below the lidar
        # Waymo vehicle frame: the ground at z = 0 (ground.patchwork_z_offset)
        (CFG.replace(**{"ground.method": "patchwork"}), 0.0),
    ],
)
def test_patchwork_finds_a_flat_ground(cfg, ground_z):
    rng = np.random.default_rng(0)
    radius, angle = rng.uniform(3, 30, 20000), rng.uniform(-np.pi, np.pi, 20000)
    plane = np.stack([radius * np.cos(angle), radius * np.sin(angle), np.full(20000, ground_z)], 1)
    pole = np.stack([np.full(500, 6.0), np.zeros(500), np.linspace(0.5, 2.7, 500) + ground_z], 1)
    points = np.concatenate([plane, pole]).astype(np.float32)
    segmenter = GroundSegmenter(cfg)
    ground = segmenter(points)
    assert ground[:20000].mean() > 0.95
    assert not ground[20000:].any()
    # Patchwork++ adapts its thresholds to what it has seen; the segmenter must not: same scan, same mask
    np.testing.assert_array_equal(segmenter(points), ground)


def test_voxel_downsample_carries_labels_back():
    points = np.array([[0.01, 0.01, 0.0], [0.05, 0.02, 0.0], [0.31, 0.0, 0.0]], np.float32)
    means, inverse = voxel_downsample(points, 0.1)
    assert len(means) == 2 and inverse[0] == inverse[1] != inverse[2]
    np.testing.assert_allclose(means[inverse[0]], [0.03, 0.015, 0.0], atol=1e-6)


def test_relabel_by_size_keeps_largest():
    raw = np.array([5, 5, 5, 2, 2, -1, 7, 7, 7, 7])
    assert relabel_by_size(raw, 2).tolist() == [1, 1, 1, -1, -1, -1, 0, 0, 0, 0]


def test_clustering_separates_blobs_deterministically():
    rng = np.random.default_rng(1)
    blobs = np.concatenate([rng.normal(c, 0.1, (200, 3)) for c in ((0, 0, 1), (5, 0, 1), (0, 6, 1))]).astype(np.float32)
    for voxel in (0.0, 0.05):  # every point, and voxel means with labels carried back
        cfg = CFG.replace(clustering={"min_cluster_size": 20, "voxel_size": voxel}).clustering
        labels = cluster_points(blobs, cfg)
        assert len(np.unique(labels[labels >= 0])) == 3
        for k in range(3):
            assert len(np.unique(labels[200 * k : 200 * (k + 1)])) == 1
        assert np.array_equal(labels, cluster_points(blobs, cfg))


def test_pairing_sanity_check_by_hand():
    src = np.array([[0, 0, 0], [2, 0, 1], [10, 0, 0], [10, 0.1, 0.1]], np.float32)
    dst = np.array([[1, 0, 0], [3, 0, 1], [10, 3, 0], [10, 13, 0.1]], np.float32)
    labels = np.array([0, 0, 1, 1])
    s, d = cluster_stats(src, labels, 2), cluster_stats(dst, labels, 2)
    np.testing.assert_allclose(s.centroid[0], [1, 0, 0.5])
    np.testing.assert_allclose(s.extent[0], [0, 1, 2])
    cfg = CFG.pairing
    # pair (0, 0): centroids 1 m apart, extents identical; pair (1, 1): dst is 100x longer (ratio 0.01 < 0.1)
    assert plausible(s, d, [0, 1], [0, 1], 3.0, cfg, 2).tolist() == [True, False]
    assert plausible(s, d, [0], [0], 0.9, cfg, 2).tolist() == [False]  # beyond the window
    assert plausible(s, d, [0], [0], 3.0, cfg, 3).tolist() == [False]  # clusters smaller than min_cluster_size


def test_confidence_formula():
    conf = match_confidence(np.array([0.0, 0.15, 0.3, 0.0]), np.array([1.0, 0.5, 0.9, 0.25]), CFG.flow, 0.3)
    np.testing.assert_allclose(conf, [1.0, 0.5, 0.0, 0.5], atol=1e-6)


# ----------------------------------------------------------------------------------------------- pipeline


def test_moving_box_flow_is_recovered(result, moving_scene):
    s = moving_scene
    err = np.linalg.norm(result.flow - s["flow"], axis=1)
    moving, static = s["moving0"], ~s["moving0"] & ~s["ground0"]
    assert err[moving].mean() < 0.03
    assert err[static].max() < 0.05
    assert result.confidence[moving].min() > 0.5
    assert len(result.pairs) == 5 and result.dropped0 == 0
    assert result.flow.dtype == np.float32 and result.confidence.dtype == np.float32
    assert set(result.timings) >= {"ground", "clustering", "pairing", "histogram", "icp", "flow", "ego_motion"}


def test_ground_points_get_exact_ego_flow_and_zero_confidence(result, moving_scene):
    s = moving_scene
    g = s["ground0"]
    np.testing.assert_array_equal(result.flow[g], ego_flow(s["pc0"][g], EGO))
    assert not result.confidence[g].any()
    assert (result.labels0[g] == -1).all()


def test_same_input_same_output(teacher, result, moving_scene):
    s = moving_scene
    again = ICPFlow(CFG)(s["pc0"], s["pc1"], s["ego"])
    np.testing.assert_array_equal(again.flow, result.flow)
    np.testing.assert_array_equal(again.confidence, result.confidence)
    np.testing.assert_array_equal(again.labels0, result.labels0)


def test_given_ground_masks_replace_segmentation(teacher, moving_scene):
    s = moving_scene
    r = ICPFlow(CFG.replace(**{"ground.method": "none"}))(s["pc0"], s["pc1"], s["ego"], s["ground0"], s["ground1"])
    assert np.linalg.norm(r.flow - s["flow"], axis=1)[s["moving0"]].mean() < 0.03
    np.testing.assert_array_equal(r.ground0, s["ground0"])


def test_stage2_pairs_far_moving_box():
    # 3.2 m sideways in 0.1 s (the box is 1.9 m wide, the window 3.34 m): two clusters, matched in stage 2
    s = scene(EGO, moving=(make_transform(translation=(0.0, 3.2, 0.0)),))
    r = ICPFlow(CFG)(s["pc0"], s["pc1"], s["ego"])
    err = np.linalg.norm(r.flow - s["flow"], axis=1)
    assert err[s["moving0"]].mean() < 0.03
    assert 2 in r.stage.tolist()


@pytest.mark.parametrize("metres", [1.0, 2.0, 3.0])
def test_a_fast_car_in_a_front_view_is_found_and_the_static_scene_stays(metres):
    """A car driving 1-3 m a frame along itself (10-30 m/s at 10 Hz), both scans cropped to a front camera's 90
    degrees while the ego drives 0.9 m: the car gets its motion, the static boxes and the ground the ego flow."""
    ego = make_transform(yaw=0.01, translation=(-0.9, 0.0, 0.0))
    s = scene(ego, seed=4, moving=(make_transform(translation=(metres, 0.0, 0.0)),))
    keep0 = np.abs(np.arctan2(s["pc0"][:, 1], s["pc0"][:, 0])) <= np.pi / 4
    keep1 = np.abs(np.arctan2(s["pc1"][:, 1], s["pc1"][:, 0])) <= np.pi / 4
    assert CFG.icp.plane_gain > 0  # the preset's plane test, with the next scan's view
    r = ICPFlow(CFG)(s["pc0"][keep0], s["pc1"][keep1], ego, s["ground0"][keep0], s["ground1"][keep1])
    error = np.linalg.norm(r.flow - s["flow"][keep0], axis=1)
    moving, ground = s["moving0"][keep0], s["ground0"][keep0]
    assert moving.sum() > 500 and error[moving].mean() < 0.05
    assert error[~moving & ~ground].max() < 1e-4 and error[ground].max() < 1e-4


def test_torch_backend_agrees_with_cpu(moving_scene):
    s = moving_scene
    cpu, batched = (
        ICPFlow(CFG.replace(icp={"max_points": 1000, "backend": b}))(s["pc0"], s["pc1"], s["ego"])
        for b in ("cpu", "torch")
    )
    np.testing.assert_array_equal(cpu.pairs, batched.pairs)
    assert np.abs(cpu.flow - batched.flow).max() < 0.01


@pytest.mark.parametrize("overrides", [{"histogram.init": "centroid"}, {"association.method": "hungarian"}])
def test_ablations_recover_the_box(overrides, moving_scene):
    s = moving_scene
    r = ICPFlow(CFG.replace(**overrides))(s["pc0"], s["pc1"], s["ego"])
    assert np.linalg.norm(r.flow - s["flow"], axis=1)[s["moving0"]].mean() < 0.05


# ----------------------------------------------------------------------------------------------- bad input


def _ego_only(r, pc0, ego):
    np.testing.assert_allclose(r.flow, ego_flow(pc0, ego), atol=1e-6)
    assert not r.confidence.any()


def test_empty_scans(teacher):
    empty = np.zeros((0, 3), np.float32)
    some = scene(EGO)["pc0"]
    r = teacher(empty, some, EGO)
    assert r.flow.shape == (0, 3) and r.confidence.shape == (0,)
    _ego_only(teacher(some, empty, EGO), some, EGO)
    _ego_only(teacher(empty[:0], empty, EGO), empty, EGO)


def test_all_ground_scan(teacher):
    flat = scene(EGO)
    pc0 = flat["pc0"][flat["ground0"]]
    _ego_only(teacher(pc0, flat["pc1"][flat["ground1"]], EGO), pc0, EGO)


def test_one_cluster_and_noise(teacher):
    rng = np.random.default_rng(3)
    blob = rng.normal((5, 0, 1), 0.2, (300, 3)).astype(np.float32)
    single = teacher(blob, blob, np.eye(4))  # one object: matched to itself or left as noise, flow 0 either way
    np.testing.assert_allclose(single.flow, 0.0, atol=1e-3)
    assert single.confidence.min() >= 0 and single.confidence.max() <= 1
    two = np.concatenate([blob, blob + np.float32([0, 8, 0])])
    r = teacher(two, two, np.eye(4))
    assert len(r.pairs) == 2
    np.testing.assert_allclose(r.flow, 0.0, atol=1e-3)
    noise = rng.uniform(-30, 30, (40, 3)).astype(np.float32) + np.float32([0, 0, 31])
    _ego_only(teacher(noise, noise, EGO), noise, EGO)


def test_identical_scans_give_zero_flow(teacher, moving_scene):
    pc = moving_scene["pc0"]
    r = teacher(pc, pc, np.eye(4))
    np.testing.assert_allclose(r.flow, 0.0, atol=1e-4)
    assert r.confidence[~moving_scene["ground0"]].min() > 0.9


def test_nan_rows_are_dropped_and_counted(teacher, moving_scene, result):
    s = moving_scene
    pc0 = s["pc0"].copy()
    pc0[[0, 7]] = np.nan
    pc0[3, 2] = np.inf
    pc1 = np.concatenate([s["pc1"], np.full((2, 3), np.nan, np.float32)])
    r = teacher(pc0, pc1, s["ego"])
    assert (r.dropped0, r.dropped1) == (3, 2)
    assert np.isfinite(r.flow).all() and not r.valid0[[0, 3, 7]].any()
    assert (r.flow[[0, 3, 7]] == 0).all() and (r.confidence[[0, 3, 7]] == 0).all()
    clean = teacher(pc0[r.valid0], pc1[:-2], s["ego"])  # dropping rows == never having had them
    np.testing.assert_array_equal(r.flow[r.valid0], clean.flow)
    np.testing.assert_array_equal(r.labels0[r.valid0], clean.labels0)


@pytest.mark.parametrize(
    "kwargs, words",
    [
        ({"ego1_from_ego0": np.diag([2.0, 1, 1, 1])}, "not rigid"),
        ({"ego1_from_ego0": np.eye(3)}, "shape"),
        ({"ground0": np.zeros(5, bool)}, "ground0"),
        ({"gap": 9}, "gap"),
    ],
)
def test_bad_arguments_are_one_line_errors(teacher, moving_scene, kwargs, words):
    s = moving_scene
    kwargs = {"ego1_from_ego0": s["ego"], **kwargs}
    with pytest.raises(ValueError, match=words) as info:
        teacher(s["pc0"], s["pc1"], **kwargs)
    assert "\n" not in str(info.value)


def test_wrong_point_shape(teacher, moving_scene):
    with pytest.raises(ValueError, match=r"ICPFlow: pc1 must be a numeric \(N, 3\) array, got float32 \(4, 2\)"):
        teacher(moving_scene["pc0"], np.zeros((4, 2), np.float32), EGO)
    with pytest.raises(ValueError, match=r"ICPFlow: pc0 has shape \(3, \d+\): a transposed scan\?"):
        teacher(moving_scene["pc0"].T, moving_scene["pc1"], EGO)


@pytest.mark.parametrize(
    "mode, passed, estimated",
    [
        ("given", True, False),
        ("given", False, True),  # a transform passed in is used; none: KISS-ICP
        ("kiss_icp", True, True),
        ("kiss_icp", False, True),  # the ablation: always estimated
    ],
)
def test_ego_motion_switch(monkeypatch, moving_scene, mode, passed, estimated):
    s = moving_scene
    guess = make_transform(yaw=0.002, translation=(0.55, 0.01, 0.0))
    calls = []
    monkeypatch.setattr(
        "icpflow.teacher.pipeline.estimate_ego_motion", lambda a, b, cfg, g0, g1: calls.append(1) or guess
    )
    result = ICPFlow(CFG.replace(**{"ego_motion.method": mode}))(s["pc0"], s["pc1"], s["ego"] if passed else None)
    assert bool(calls) == estimated
    np.testing.assert_array_equal(result.ego1_from_ego0, guess if estimated else s["ego"])


# ----------------------------------------------------------------------------------------------- long horizon


def test_long_horizon_direct_and_tracker(teacher):
    step = make_transform(yaw=0.01, translation=(0.6, 0.0, 0.0))
    box_step = make_transform(translation=(0.6, 0.8, 0.0))
    scans = []
    for k in range(3):
        s = scene(np.linalg.matrix_power(step, k), seed=k, moving=(np.linalg.matrix_power(box_step, k),))
        scans.append(s["pc1"] if k else s["pc0"])
    truth = scene(np.linalg.matrix_power(step, 2), seed=0, moving=(np.linalg.matrix_power(box_step, 2),))
    moving = truth["moving0"]
    # The 4.5 m box slides 1.2 m along its own axis over the two frames (a direct (0, 2) pair); the tracker chains
    # two 1-frame steps.
    for mode in ("direct", "tracker"):
        r = long_horizon_flow(teacher, scans, [step, step], mode=mode)
        np.testing.assert_allclose(r.ego_k_from_0, step @ step)
        err = np.linalg.norm(r.flow - truth["flow"], axis=1)
        assert err[moving].mean() < 0.02, mode
        assert err[~moving].max() < 0.05, mode
        assert r.confidence[moving].min() > 0.3, mode
    assert r.chained[moving].all()
    with pytest.raises(ValueError, match="scans"):
        long_horizon_flow(teacher, scans[:1])
