"""Per-cluster kernels of the ICP-Flow teacher: histogram initialisation, ICP, checks and association."""

import numpy as np
import pytest

from icpflow.core.geometry import euler_angles, invert, make_transform, transform_points
from icpflow.teacher.association import associate
from icpflow.teacher.checks import passes
from icpflow.teacher.config import ChecksConfig, HistogramConfig, ICPConfig, ICPFlowConfig
from icpflow.teacher.histogram import centroid_translation, initial_translation, initial_translations
from icpflow.teacher.registration import register_clusters

HIST = HistogramConfig(max_points=300)  # the av2 preset's vote
ICP = ICPConfig()


def _box_surface(n, size=(4.4, 1.8, 1.5), seed=0):
    """n points on the surface of an axis-aligned box with its base centred at the origin, float32."""
    rng = np.random.default_rng(seed)
    lo = np.array([-size[0] / 2, -size[1] / 2, 0.0])
    hi = np.array([size[0] / 2, size[1] / 2, size[2]])
    points = rng.uniform(lo, hi, (n, 3))
    axis = rng.integers(0, 3, n)
    points[np.arange(n), axis] = np.where(rng.random(n) < 0.5, lo[axis], hi[axis])
    return points.astype(np.float32)


def _noisy(points, sigma, seed):
    return (points + np.random.default_rng(seed).normal(0.0, sigma, points.shape)).astype(np.float32)


def _rotation_error(a, b):
    return float(np.arccos(np.clip((np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2, -1, 1)))


# ------------------------------------------------------------------------------------------------- histogram


def test_histogram_bin_centre_is_returned_exactly():
    src = _box_surface(200)
    # A translation on a bin centre comes back exactly; the reference would return the lower edge (-0.05 m).
    translations, scores = initial_translations([(src, src + np.float32([1.3, -0.7, 0.1]))], [3.0], HIST)
    np.testing.assert_allclose(translations[0], [1.3, -0.7, 0.1], atol=1e-9)
    assert scores[0] < 1e-6
    # Off-centre by 0.03 m: the centre of the bin holding it.
    translations, _ = initial_translations([(src, src + np.float32([1.33, -0.67, 0.0]))], [3.0], HIST)
    np.testing.assert_allclose(translations[0], [1.3, -0.7, 0.0], atol=1e-9)


def test_histogram_recovers_translation_with_noise_partial_view():
    src = _box_surface(600, seed=1)
    truth = np.array([2.46, 1.12, 0.03])
    moved = _noisy(src + truth, 0.02, seed=2)
    partial = moved[(moved[:, 1] > truth[1] + 0.3) & (moved[:, 0] < truth[0] + 1.0)]  # a corner seen in dst
    translations, scores = initial_translations([(src, partial)], [3.34], HIST)
    np.testing.assert_allclose(translations[0], [2.5, 1.1, 0.0], atol=1e-9)  # the bin holding the truth
    assert scores[0] < 0.15  # mean spacing of 300 points on the 34 m2 box surface is about 0.1 m


def test_histogram_scoring_overrules_a_stronger_distractor_peak():
    # src: a wall patch and a box. dst: both moved by the truth, plus two more copies of the wall 1 m further in
    # y. Wall-to-copies votes outnumber the true ones, but only the truth also brings the box onto its copy.
    xz = np.stack(np.meshgrid(np.arange(0, 2, 0.1), np.arange(0, 1.5, 0.1)), -1).reshape(-1, 2)
    wall = np.column_stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]])
    src = np.concatenate([wall, _box_surface(200, size=(1, 1, 1), seed=3) + [1.0, 2.5, 0.0]]).astype(np.float32)
    truth = np.array([1.5, -0.8, 0.0])
    copies = [wall + truth + [0.0, 1.0, 0.0], wall + truth + [0.0, 1.03, 0.0]]
    dst = np.concatenate([src + truth, *copies]).astype(np.float32)
    params = HistogramConfig(max_points=2000)
    top1, _ = initial_translations([(src, dst)], [3.0], HistogramConfig(max_points=2000, top_k=1))
    assert np.abs(top1[0] - truth).max() > 0.5  # the strongest peak alone is the distractor
    translations, scores = initial_translations([(src, dst)], [3.0], params)
    np.testing.assert_allclose(translations[0], truth, atol=1e-9)
    assert scores[0] < 1e-6


def test_histogram_zero_candidate_for_static_cluster():
    src = _box_surface(400, seed=3)
    translations, scores = initial_translations([(src, _noisy(src, 0.01, 4))], [3.34], HIST)
    assert np.array_equal(translations[0], np.zeros(3))
    # No vote inside the window at all: the zero translation is the only candidate.
    far = src + np.float32([20.0, 0.0, 0.0])
    translations, scores = initial_translations([(src, far)], [3.34], HIST)
    assert np.array_equal(translations[0], np.zeros(3)) and 15.6 < scores[0] < 20.0  # 15.6 to 20 m apart


def test_histogram_batch_matches_single_calls_and_is_deterministic():
    pairs = [
        (_box_surface(500 + 50 * k, seed=k), _box_surface(450, seed=k + 10) + np.float32([k * 0.4, 0, 0]))
        for k in range(4)
    ]
    batch, batch_scores = initial_translations(pairs, np.full(4, 3.0), HIST)
    for k, pair in enumerate(pairs):
        single, score = initial_translations([pair], [3.0], HIST)
        np.testing.assert_array_equal(single[0], batch[k])
        assert score[0] == batch_scores[k]
    again, _ = initial_translations(pairs, np.full(4, 3.0), HIST)
    np.testing.assert_array_equal(again, batch)
    np.testing.assert_allclose(batch[:, 0], [0.0, 0.4, 0.8, 1.2], atol=0.1 + 1e-9)


def test_centroid_translation():
    src = np.float32([[0, 0, 0], [2, 0, 0]])
    np.testing.assert_allclose(centroid_translation(src, src + np.float32([1, 2, 3])), [1, 2, 3], atol=1e-6)
    np.testing.assert_array_equal(centroid_translation(src[:0], src), np.zeros(3))


# ------------------------------------------------------------------------------------------------------ ICP


def test_icp_recovers_rigid_transform_from_nearby_init():
    src = _box_surface(800, seed=5)
    truth = make_transform(yaw=0.15, translation=(1.8, -0.6, 0.02))
    dst = _noisy(transform_points(truth, src), 0.005, seed=6)
    init = make_transform(yaw=0.12, translation=(1.85, -0.55, 0.0))
    result = register_clusters([(src, dst)], init[None], ICP)
    assert np.abs(result.transforms[0, :3, 3] - truth[:3, 3]).max() < 0.01
    assert _rotation_error(result.transforms[0], truth) < np.radians(0.2)
    assert result.iou_ratio[0] > 0.95 and result.mean_error[0] < 0.01
    assert 1 <= result.iterations[0] < ICP.max_iter


@pytest.mark.parametrize("yaw_only", [False, True])
def test_icp_does_not_depend_on_the_grid_cell(yaw_only):
    # The correspondence search is exact whatever the cell size of the fixed cloud's grid, so the registration
    # shares the quality grid (0.3 m cells) with no change to any transform: 0.1 m (the truncation), 0.3 m and
    # 2 m cells give the same iterations and bit-identical transforms, point-to-point and point-to-plane.
    from icpflow.scans.neighbours import build_grid
    from icpflow.teacher.registration.icp import icp_point_to_plane, icp_point_to_point, normals

    src = _box_surface(1500, seed=11).astype(np.float64)
    truth = make_transform(yaw=0.08, translation=(0.9, 0.3, 0.05))
    dst = _noisy(transform_points(truth, _box_surface(1400, seed=12)), 0.01, seed=13).astype(np.float64)
    init = make_transform(yaw=0.05, translation=(0.85, 0.35, 0.0))
    dst_normals = normals(dst)
    point, plane = [], []
    for cell in (0.1, 0.3, 2.0):
        grid = build_grid(dst, cell)
        point.append(icp_point_to_point(src, dst, grid, cell, init, 0.1, 100, 1e-6, yaw_only))
        plane.append(icp_point_to_plane(src, dst, dst_normals, grid, cell, init, 0.1, 30))
    for results in (point, plane):
        assert results[0][1] >= 2
        for transform, iterations in results[1:]:
            assert iterations == results[0][1]
            np.testing.assert_array_equal(transform, results[0][0])
    assert np.abs(point[0][0][:3, 3] - truth[:3, 3]).max() < 0.05


def test_icp_keeps_initial_transform_when_it_got_worse():
    # Fixed: two parallel planes y = 0 and y = 1. Moving: a small patch 5 cm above y = 0 (inside the 0.1 m
    # correspondence range) and a large patch 12 cm below y = 1 (outside it). ICP snaps the small patch onto
    # y = 0, which pushes the large patch 17 cm from y = 1: the mean distance grows, so the start is kept.
    grid = np.stack(np.meshgrid(np.arange(10) * 0.1, np.arange(10) * 0.1), -1).reshape(-1, 2)
    plane = lambda y, xz: np.column_stack([xz[:, 0], np.full(len(xz), y), xz[:, 1]])  # noqa: E731
    fixed = np.concatenate([plane(0.0, grid), plane(1.0, grid)]).astype(np.float32)
    moving = np.concatenate([plane(0.05, grid[:9]), plane(0.88, grid[20:70])]).astype(np.float32)
    for backend in ("cpu", "torch"):
        result = register_clusters([(moving, fixed)], np.eye(4)[None], ICPConfig(backend=backend))
        assert result.iterations[0] >= 1
        np.testing.assert_array_equal(result.transforms[0], np.eye(4))
        # Truncated ICP alone moves 5 cm down: without the check the result would differ from the start.
        assert result.mean_error[0] == pytest.approx((9 * 0.05 + 50 * 0.12) / 59, abs=1e-6)


def test_smaller_cluster_is_registered_and_result_inverted():
    big = _box_surface(900, seed=7)
    truth = make_transform(yaw=-0.1, translation=(0.9, 0.4, 0.0))
    small = transform_points(truth, big)[::3]
    init = make_transform(yaw=-0.08, translation=(0.92, 0.38, 0.0))
    forward = register_clusters([(big, small)], init[None], ICP)  # src larger: roles swapped inside
    backward = register_clusters([(small, big)], invert(init)[None], ICP)
    np.testing.assert_allclose(forward.transforms[0], truth, atol=2e-3)
    np.testing.assert_allclose(forward.transforms[0], invert(backward.transforms[0]), atol=1e-9)
    assert forward.mean_error[0] == pytest.approx(backward.mean_error[0], abs=1e-9)
    assert forward.iou_ratio[0] == pytest.approx(backward.iou_ratio[0], abs=1e-9)


def test_error_and_iou_match_exact_nearest_neighbours():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(11)
    pairs = [
        (_box_surface(300, seed=12), _noisy(_box_surface(500, seed=13), 0.05, 14)),  # overlapping, noisy
        (_box_surface(200, seed=15), _box_surface(400, seed=16) + np.float32([7.0, 3.0, 0.5])),  # far apart
        (rng.uniform(-5, 5, (400, 3)).astype(np.float32), rng.uniform(-3, 8, (250, 3)).astype(np.float32)),
    ]
    result = register_clusters(pairs, np.tile(np.eye(4), (3, 1, 1)), ICPConfig(max_iter=3))
    for (src, dst), transform, error, iou in zip(pairs, result.transforms, result.mean_error, result.iou_ratio):
        moved = transform_points(transform, src.astype(np.float64))
        fwd, _ = cKDTree(dst).query(moved)
        bwd, _ = cKDTree(moved).query(dst)
        assert error == pytest.approx(min(fwd.mean(), bwd.mean()), rel=1e-6)
        n = len(src) + len(dst)
        i_f, i_b = (fwd < 0.1).sum(), (bwd < 0.1).sum()
        assert iou == pytest.approx(min(i_f / (n - i_f), i_b / (n - i_b)), abs=1e-9)


def test_cpu_and_torch_backends_agree():
    rng = np.random.default_rng(8)
    pairs, inits = [], []
    for k in range(6):
        src = _box_surface(int(rng.integers(150, 400)), seed=20 + k)
        truth = make_transform(rng.uniform(-0.3, 0.3), (*rng.uniform(-2, 2, 2), 0.0))
        dst = _noisy(transform_points(truth, _box_surface(int(rng.integers(150, 400)), seed=40 + k)), 0.01, k)
        pairs.append((src, dst))
        inits.append(truth @ make_transform(rng.uniform(-0.05, 0.05), (*rng.uniform(-0.08, 0.08, 2), 0.0)))
    pairs.append((pairs[0][0], pairs[0][0][:0]))  # an empty cluster keeps its start
    inits.append(np.eye(4))
    cpu = register_clusters(pairs, np.array(inits), ICP)
    gpu = register_clusters(pairs, np.array(inits), ICPConfig(backend="torch"))
    for a, b in zip(cpu.transforms, gpu.transforms):
        assert np.abs(a[:3, 3] - b[:3, 3]).max() < 1e-3 and _rotation_error(a, b) < 1e-3
    np.testing.assert_allclose(cpu.mean_error[:-1], gpu.mean_error[:-1], atol=1e-4)
    np.testing.assert_allclose(cpu.iou_ratio, gpu.iou_ratio, atol=1e-3)
    assert cpu.mean_error[-1] == np.inf and cpu.iou_ratio[-1] == 0.0 and gpu.mean_error[-1] == np.inf
    np.testing.assert_array_equal(cpu.transforms[-1], np.eye(4))
    again = register_clusters(pairs, np.array(inits), ICP)
    np.testing.assert_array_equal(again.transforms, cpu.transforms)


def test_yaw_only_icp_keeps_objects_upright():
    # icp.dof="yaw" recovers the yaw and the 3D translation with exactly zero roll and pitch, on both backends.
    src = _box_surface(800, seed=9)
    truth = make_transform(yaw=0.1, translation=(0.8, -0.2, 0.05))
    dst = _noisy(transform_points(truth, src), 0.01, seed=10)
    init = make_transform(yaw=0.08, translation=(0.75, -0.15, 0.0))
    for backend in ("cpu", "torch"):
        result = register_clusters([(src, dst)], init[None], ICPConfig(dof="yaw", backend=backend))
        roll, pitch, angle = euler_angles(result.transforms[0])
        assert roll == 0.0 and pitch == 0.0
        assert angle == pytest.approx(0.1, abs=2e-3)
        np.testing.assert_allclose(result.transforms[0, :3, 3], truth[:3, 3], atol=0.01)


def test_settings_come_from_the_config():
    cfg = ICPFlowConfig.preset("av2", histogram={"max_points": 123, "top_k": 2}, icp={"max_points": 456, "dof": "yaw"})
    assert cfg.histogram == HistogramConfig(max_points=123, top_k=2, axis_min_extent=3.0)
    assert cfg.icp == ICPConfig(max_points=456, dof="yaw", static_tolerance=0.25, plane_gain=1.0)
    src = _box_surface(200)
    translation, score = initial_translation(src, src + np.float32([0.5, 0.0, 0.0]), 2.0, cfg.histogram, cfg.seed)
    np.testing.assert_allclose(translation, [0.5, 0.0, 0.0], atol=1e-9)
    result = register_clusters([(src, src)], np.eye(4)[None], cfg.icp, cfg.seed)
    np.testing.assert_allclose(result.transforms[0], np.eye(4), atol=1e-9)
    fails = passes(make_transform(translation=(0.1, 0, 0))[None], [0.25], [0.5], 2.0, cfg.checks)  # max_error 0.2
    assert not fails[0]


# --------------------------------------------------------------------------------------------------- checks


THRESHOLDS = ChecksConfig(min_iou=0.2, max_roll_pitch_deg=9.0, max_error=0.2)


def test_checks_reject_each_failure_alone():
    good = make_transform(yaw=0.5, translation=(1.0, 0.5, 0.0))
    cases = {
        "good": (good, 0.05, 0.6, True),
        "too far": (make_transform(translation=(2.9, 0.0, 0.0)), 0.05, 0.6, False),
        "low iou": (good, 0.05, 0.19, False),
        "roll": (make_transform(roll=np.radians(9.5)), 0.05, 0.6, False),
        "pitch": (make_transform(pitch=np.radians(-9.5)), 0.05, 0.6, False),
        "pitch inside": (make_transform(pitch=np.radians(8.5), yaw=3.0), 0.05, 0.6, True),
        "error": (good, 0.21, 0.6, False),
        "nan": (good, np.nan, 0.6, False),
    }
    transforms = np.array([c[0] for c in cases.values()])
    result = passes(transforms, [c[1] for c in cases.values()], [c[2] for c in cases.values()], 2.5, THRESHOLDS)
    assert dict(zip(cases, result.tolist())) == {name: c[3] for name, c in cases.items()}


def test_checks_use_centroid_displacement_when_given():
    # A 0.2 rad turn about the origin moves a cluster at x = 20 m by about 4 m, though T's translation is 0.
    turn = make_transform(yaw=0.2)
    centroid = np.array([[20.0, 0.0, 0.0]])
    assert passes(turn[None], [0.05], [0.6], 2.5, THRESHOLDS)[0]
    assert not passes(turn[None], [0.05], [0.6], 2.5, THRESHOLDS, src_centroids=centroid)[0]
    assert passes(turn[None], [0.05], [0.6], 4.5, THRESHOLDS, src_centroids=centroid)[0]


# ---------------------------------------------------------------------------------------------- association


def test_argmin_and_hungarian_differ_on_hand_case():
    # Sources A=0, B=1; destinations X=10, Y=11. Costs: A-X 1, A-Y 2, B-X 1.5, B-Y 10, plus B-Y failing checks.
    src = np.array([0, 0, 1, 1, 1])
    dst = np.array([10, 11, 10, 11, 11])
    cost = np.array([1.0, 2.0, 1.5, 10.0, 0.1])
    ok = np.array([True, True, True, True, False])
    # argmin: each source its cheapest passing destination, both pick X.
    assert associate(src, dst, cost, ok, "argmin").tolist() == [True, False, True, False, False]
    # Hungarian: one-to-one with the lowest total, A-Y + B-X = 3.5 < A-X + B-Y = 11.
    assert associate(src, dst, cost, ok, "hungarian").tolist() == [False, True, True, False, False]


def test_association_edge_cases():
    none = associate([0, 1], [5, 5], [1.0, 2.0], [False, False])
    assert none.tolist() == [False, False]
    tie = associate([0, 0], [5, 6], [1.0, 1.0], [True, True])  # ties go to the first listed pair
    assert tie.tolist() == [True, False]
    # Hungarian prefers more matches: one source, two destinations, only one can be taken.
    assert associate([0, 0, 1], [5, 6, 5], [1.0, 0.5, 3.0], [True] * 3, "hungarian").tolist() == [False, True, True]
    with pytest.raises(ValueError, match="method"):
        associate([0], [1], [1.0], [True], "greedy")


def test_static_pairs_keep_the_identity_when_a_slide_fits_barely_better():
    import dataclasses

    from icpflow.teacher.pipeline import _prefer_static

    # A 6 m x 3 m wall sampled at random by two scans: a 0.1 m slide along it fits about as well as no motion.
    # A car that moved 0.3 m fits far worse at the identity than at its motion.
    rng = np.random.default_rng(0)
    wall0, wall1 = (
        np.column_stack([rng.uniform(0, 6, 2000), rng.normal(0, 0.01, 2000), rng.uniform(0, 3, 2000)]).astype(
            np.float32
        )
        for _ in range(2)
    )
    car = _box_surface(600, seed=3)
    motion = make_transform(translation=(0.3, 0.1, 0.0))
    moved = _noisy(transform_points(motion, car), 0.01, 4)
    clouds = [(wall0, wall1), (car, moved)]
    transforms = np.stack([make_transform(translation=(0.1, 0.0, 0.0)), motion])
    result = register_clusters(clouds, transforms, dataclasses.replace(ICP, max_iter=0))  # quality only
    slid = result.mean_error.copy()
    _prefer_static(result, clouds, dataclasses.replace(ICP, static_tolerance=0.25))
    np.testing.assert_array_equal(result.transforms[0], np.eye(4))
    assert result.mean_error[0] <= 1.25 * slid[0]  # the identity's own error replaced the slide's
    np.testing.assert_array_equal(result.transforms[1], motion)
    assert result.mean_error[1] == slid[1]


def test_identity_quality_measured_in_the_registration_pass_equals_a_separate_pass():
    import dataclasses

    # pipeline._prefer_static reads the identity's quality from the registration itself: it must be exactly what a
    # registration with no iteration measures (both roles of the smaller cluster, a pair with an empty cluster)
    car = _box_surface(600, seed=3)
    moved = _noisy(transform_points(make_transform(0.2, (0.4, 0.1, 0.0)), car), 0.01, 4)
    clouds = [(car, moved), (moved[:300], car), (car, np.zeros((0, 3), np.float32))]
    inits = np.tile(np.eye(4), (3, 1, 1))
    inits[:, :3, 3] = (0.3, 0.0, 0.0)
    joint = register_clusters(clouds, inits, params=ICP, identity=True)
    still = register_clusters(clouds, np.tile(np.eye(4), (3, 1, 1)), params=dataclasses.replace(ICP, max_iter=0))
    np.testing.assert_array_equal(joint.identity_error, still.mean_error)
    np.testing.assert_array_equal(joint.identity_iou, still.iou_ratio)
    plain = register_clusters(clouds, inits, params=ICP)
    assert plain.identity_error is None
    np.testing.assert_array_equal(joint.transforms, plain.transforms)  # the registration itself is unchanged
    np.testing.assert_array_equal(joint.mean_error, plain.mean_error)


def test_coarse_to_fine_in_one_call_equals_the_stages_run_one_by_one():
    # register_stages_cpu runs every truncation of a coarse-to-fine ICP in one compiled call: the transforms, the
    # last stage's quality, the identity's and that of a per-point flow must be those of register_batch_cpu called
    # stage by stage (each from the last one's transforms), bit for bit, on pairs where the coarse stages matter
    # (starts 1-2 m short), where ICP makes things worse (the start is kept) and on empty clouds.
    from icpflow.teacher.registration.cpu import register_batch_cpu, register_stages_cpu

    rng = np.random.default_rng(21)
    movings, fixeds, givens, starts = [], [], [], []
    for k in range(6):
        src = _box_surface(150 + 40 * k, seed=30 + k).astype(np.float64)
        truth = make_transform(yaw=0.05 * k - 0.1, translation=(1.5 + 0.3 * k, -0.4, 0.02))
        movings.append(src)
        fixeds.append(_noisy(transform_points(truth, _box_surface(200, seed=40 + k)), 0.02, 50 + k).astype(np.float64))
        givens.append(src + truth[:3, 3] + rng.normal(0, 0.1, src.shape))  # a per-point flow near the truth
        starts.append(make_transform(translation=(0.4 * k, 0.1, 0.0)))  # 1.5-2 m short at first
    movings.append(np.zeros((0, 3)))
    fixeds.append(fixeds[0])
    givens.append(np.zeros((0, 3)))
    starts.append(np.eye(4))
    starts = np.stack(starts)
    stages = (2.0, 1.0, 0.3, 0.1)
    transforms = starts
    for index, max_corr in enumerate(stages):
        last = index == len(stages) - 1
        params = ICPConfig(max_corr=max_corr, max_iter=40, dof="yaw")
        transforms, errors, ious, _, still_errors, still_ious, *_ = register_batch_cpu(
            movings, fixeds, transforms, params, identity=last
        )
    measure = ICPConfig(max_corr=stages[-1], max_iter=0)
    _, given_errors, given_ious, *_ = register_batch_cpu(
        givens, fixeds, np.tile(np.eye(4), (len(givens), 1, 1)), measure
    )
    result = register_stages_cpu(movings, fixeds, givens, starts, stages, 40, ICPConfig().rel_rmse, yaw_only=True)
    for got, want in zip(result, (transforms, errors, ious, still_errors, still_ious, given_errors, given_ious)):
        np.testing.assert_array_equal(got, want)
    assert np.abs(result[0][:6, :3, 3] - starts[:6, :3, 3]).max() > 1.0  # the coarse stages moved the boxes
    # the identity's quality only where asked (the refinement's slow components): the rest unchanged, inf and 0
    asked = np.arange(len(starts)) % 2 == 0
    some = register_stages_cpu(movings, fixeds, givens, starts, stages, 40, ICPConfig().rel_rmse, True, asked)
    for index, (got, want) in enumerate(zip(some, result)):
        if index in (3, 4):
            np.testing.assert_array_equal(got[asked], want[asked])
            assert np.all(got[~asked] == (np.inf if index == 3 else 0.0))
        else:
            np.testing.assert_array_equal(got, want)
    assert np.isfinite(result[3][~asked][:2]).all()  # so the unasked ones were measured before


def test_nearest_distances_are_exact():
    from scipy.spatial import cKDTree

    from icpflow.scans.neighbours import build_grid, nearest_distances

    rng = np.random.default_rng(3)
    points = rng.uniform(-4, 4, (700, 3))
    query = np.concatenate([rng.uniform(-5, 5, (300, 3)), rng.uniform(20, 30, (20, 3))])  # some far outside
    truth = cKDTree(points).query(query)[0]
    reach = rng.uniform(0, 1, len(query)) * truth * 2  # about half the points nearer than their reach
    for cell in (0.1, 0.3, 2.0):
        grid = build_grid(points, cell)
        got = nearest_distances(query, points, grid, cell, np.full(len(query), np.inf))
        np.testing.assert_allclose(got, truth, rtol=1e-12)
        bounded = nearest_distances(query, points, grid, cell, reach)
        inside = truth < reach
        assert 0.3 < inside.mean() < 0.7 and np.array_equal(bounded[inside], got[inside])
        assert np.all(np.isinf(bounded[~inside]))


def test_the_grid_sorts_points_by_column_then_height_cell_stably():
    """``build_grid``'s counting sorts give the order of a stable sort by (xy column, z cell): within a cell, the
    points in their input order (repeated points included)."""
    from icpflow.scans.neighbours import build_grid

    rng = np.random.default_rng(4)
    cloud = rng.uniform(-6, 6, (3000, 3))
    for points in (cloud, np.repeat(cloud[:50], 3, axis=0), np.zeros((1, 3)), cloud[:, [0, 0, 2]]):
        for cell in (0.2, 1.0, 20.0):
            origin, dims, starts, z_sorted, order = build_grid(points, cell)
            cells = np.minimum(((points - origin) / cell).astype(np.int64), dims[:3] - 1)  # dims[3]: narrowed (0 here)
            columns = cells[:, 0] * dims[1] + cells[:, 1]
            expected = np.lexsort((np.arange(len(points)), cells[:, 2], columns))
            assert np.array_equal(order, expected) and np.array_equal(z_sorted, cells[expected, 2])
            assert dims[3] == 0
            assert np.array_equal(starts, np.searchsorted(columns[expected], np.arange(dims[0] * dims[1] + 1)))


def test_k_nearest_neighbours_are_exact():
    """``k_nearest`` gives scipy's k nearest (same points, same order, same distances) on a scan-like cloud (planes and
    sparse clutter), for queries near it and far outside (past the shells: a full scan), with fewer points than k
    (the rest -1) and within a reach (none there: -1)."""
    from scipy.spatial import cKDTree

    from icpflow.scans.neighbours import MAX_KNN_SHELL, build_grid, k_nearest

    rng = np.random.default_rng(5)
    ground = np.column_stack([rng.uniform(-30, 30, (6000, 2)), rng.normal(0.0, 0.02, 6000)])
    wall = np.column_stack([rng.uniform(-30, 30, 2000), np.full(2000, 8.0), rng.uniform(0, 3, 2000)])
    points = np.concatenate([ground, wall, rng.uniform(-40, 40, (300, 3))])
    query = np.concatenate(
        [points[rng.choice(len(points), 500)] + rng.normal(0, 0.05, (500, 3)), rng.uniform(-90, 90, (60, 3))]
    )
    tree = cKDTree(points)
    for cell in (0.25, 0.5, 2.0):
        grid = build_grid(points, cell)
        squared, index = k_nearest(query, points, grid, cell, 10, np.inf, MAX_KNN_SHELL, True)
        distance, expected = tree.query(query, k=10)
        assert np.array_equal(index, expected)
        np.testing.assert_allclose(np.sqrt(squared), distance, rtol=1e-12)
        squared, index = k_nearest(query, points, grid, cell, 1, 0.3**2, MAX_KNN_SHELL, True)
        distance, expected = tree.query(query, distance_upper_bound=0.3)
        assert np.array_equal(index[:, 0], np.where(np.isfinite(distance), expected, -1))
        assert np.all(np.isfinite(distance) == (squared[:, 0] < 0.3**2))
    few = points[:4]
    squared, index = k_nearest(query, few, build_grid(few, 0.5), 0.5, 6, np.inf, MAX_KNN_SHELL, True)
    assert np.array_equal(index[:, :4], cKDTree(few).query(query, k=4)[1]) and (index[:, 4:] == -1).all()
    assert np.isinf(squared[:, 4:]).all()


def _scan_lines(heights, seed):
    """A 6 m x 3 m wall (the plane y = 0) as a scan draws it: horizontal lines at ``heights`` (m), points 0.05 m
    apart along them."""
    rng = np.random.default_rng(seed)
    x = np.arange(0.0, 6.0, 0.05)
    rows = [np.column_stack([x, rng.normal(0, 0.005, len(x)), np.full(len(x), h)]) for h in heights]
    return np.concatenate(rows).astype(np.float32)


def test_plane_errors_do_not_reward_a_slide_along_a_surface():
    from icpflow.teacher.registration import plane_errors

    wall0, wall1 = _scan_lines(np.arange(0, 3, 0.1), 0), _scan_lines(np.arange(0.05, 3, 0.1), 1)
    slide = make_transform(translation=(0.0, 0.0, 0.05))  # lays the lines of one scan onto the other's
    push = make_transform(translation=(0.0, 0.1, 0.0))  # off the wall
    still, moved = plane_errors([(wall0, wall1)] * 2, np.stack([slide, push]), max_points=10000)
    assert still[0] < 0.01 and moved[0] < 0.01  # on the plane either way
    assert moved[1] > 0.09  # a motion off the plane is measured in full
    empty = plane_errors([(wall0, np.zeros((0, 3), np.float32))], slide[None], max_points=10000)
    assert np.isinf(empty[0]).all() and np.isinf(empty[1]).all()


def test_a_wall_drawn_by_other_scan_lines_stays_static_and_movers_keep_their_motion():
    import dataclasses

    from icpflow.teacher.pipeline import _prefer_static

    # The next scan draws the wall 0.05 m higher: a 0.05 m slide up lays its lines onto the first scan's, a better
    # point-to-point fit than no motion (what the static tolerance alone keeps), and no better a plane's fit.
    # A car that moved 0.15 m (under plane_reach) and one that moved 0.8 m fit the plane far better at their motion.
    wall0, wall1 = _scan_lines(np.arange(0, 3, 0.1), 0), _scan_lines(np.arange(0.05, 3, 0.1), 1)
    car = _box_surface(600, seed=3)
    slow, fast = make_transform(translation=(0.15, 0.05, 0.0)), make_transform(0.05, (0.8, 0.1, 0.0))
    clouds = [(wall0, wall1), (car, _noisy(transform_points(slow, car), 0.01, 4))]
    clouds.append((car, _noisy(transform_points(fast, car), 0.01, 5)))
    transforms = np.stack([make_transform(translation=(0.0, 0.0, 0.05)), slow, fast])
    tolerance_only = dataclasses.replace(ICP, static_tolerance=0.25)
    result = register_clusters(clouds, transforms, dataclasses.replace(ICP, max_iter=0))
    _prefer_static(result, clouds, tolerance_only)
    np.testing.assert_array_equal(result.transforms[0], transforms[0])  # the slide fits better point to point
    result = register_clusters(clouds, transforms, dataclasses.replace(ICP, max_iter=0))
    _prefer_static(result, clouds, dataclasses.replace(tolerance_only, plane_gain=1.0))
    np.testing.assert_array_equal(result.transforms[0], np.eye(4))
    np.testing.assert_array_equal(result.transforms[1], slow)
    np.testing.assert_array_equal(result.transforms[2], fast)


def _poles(xs, y=3.0, seed=0):
    """Vertical poles 0.15 m in radius and 2 m tall at (x, y) for each x in ``xs``, drawn 0.1 m apart in height."""
    rng = np.random.default_rng(seed)
    angle = rng.uniform(0, 2 * np.pi, (len(xs), 400))
    height = rng.uniform(0, 2, (len(xs), 400))
    xs = np.asarray(xs, float)[:, None]
    return np.stack([xs + 0.15 * np.cos(angle), y + 0.15 * np.sin(angle), height], axis=-1).reshape(-1, 3)


def test_a_scan_view_covers_the_azimuths_of_its_points():
    from icpflow.teacher.visibility import ScanView

    turn = np.linspace(-np.pi, np.pi, 5000, endpoint=False)
    assert ScanView.of(np.column_stack([10 * np.cos(turn), 10 * np.sin(turn), np.zeros_like(turn)])).full
    front = turn[np.abs(turn) <= np.pi / 4]  # a front camera's 90 degrees
    view = ScanView.of(np.column_stack([10 * np.cos(front), 10 * np.sin(front), np.zeros_like(front)]))
    assert not view.full
    np.testing.assert_array_equal(view.sees(np.array([[5.0, 1.0, 0.0], [1.0, 5.0, 0.0], [-5.0, 0.0, 2.0]])), [1, 0, 0])


def test_the_plane_test_leaves_out_what_the_next_scan_could_not_see():
    import dataclasses

    from icpflow.teacher.pipeline import _prefer_static
    from icpflow.teacher.visibility import ScanView

    # A row of five static poles along y = 3 at the edge of a front view (azimuth <= 45 degrees): the next scan sees
    # the three at x >= 3.5. Slid one gap (1.5 m) along the row, the whole row overlays the three drawn poles better
    # than where it stands, since its two unseen poles have no partner there; left out as unseen, the identity fits
    # them exactly. A car in the view that moved 0.8 m keeps its motion either way.
    row, drawn = _poles([0.5, 2.0, 3.5, 5.0, 6.5]), _poles([3.5, 5.0, 6.5], seed=1)
    car = _box_surface(600, seed=3) + np.array([12.0, 0.0, 0.0])
    fast = make_transform(0.05, (0.8, 0.1, 0.0))
    clouds = [(row, drawn), (car, _noisy(transform_points(fast, car), 0.01, 5))]
    transforms = np.stack([make_transform(translation=(1.5, 0.0, 0.0)), fast])
    sector = np.linspace(-np.pi / 4, np.pi / 4, 2000)
    view = ScanView.of(np.column_stack([20 * np.cos(sector), 20 * np.sin(sector), np.zeros_like(sector)]))
    params = dataclasses.replace(ICP, static_tolerance=0.25, plane_gain=1.0)
    decisions = []
    for seen in (None, view):
        result = register_clusters(clouds, transforms, dataclasses.replace(ICP, max_iter=0), identity=True)
        result.identity_error = 2 * result.mean_error + 0.1  # a point-to-point fit that prefers the slide
        _prefer_static(result, clouds, params, view=seen)
        decisions.append(result.transforms.copy())
    np.testing.assert_array_equal(decisions[0], transforms)  # without the view the slide is kept
    np.testing.assert_array_equal(decisions[1][0], np.eye(4))
    np.testing.assert_array_equal(decisions[1][1], fast)


def test_a_static_pole_matched_to_its_neighbour_finds_its_twin_and_a_mover_does_not():
    from icpflow.teacher.pairing import cluster_stats
    from icpflow.teacher.pipeline import _twin_shares

    # pc0: pole A and a car. pc1: A's own next points labelled 1 (the clustering split them off), the neighbouring
    # pole B 1.5 m on (label 3), the car 1 m on, over half its old place (label 2).
    pole_a, pole_a1, pole_b1 = _poles([0.0]), _poles([0.0], seed=1), _poles([1.5], seed=2)
    car = _box_surface(600, seed=3) + np.array([10.0, 0.0, 0.0])
    car1 = _box_surface(600, seed=4) + np.array([11.0, 0.0, 0.0])
    dst = np.concatenate([pole_a1, pole_b1, car1])
    stats = cluster_stats(dst, np.repeat([1, 3, 2], [len(pole_a1), len(pole_b1), len(car1)]), 4)
    clouds = [(pole_a, pole_b1), (pole_a, pole_a1), (car, car1)]
    slide, drive = make_transform(translation=(1.5, 0.0, 0.0)), make_transform(translation=(1.0, 0.0, 0.0))
    transforms = np.stack([slide, np.eye(4), drive])
    shares = _twin_shares(dst, stats, clouds, np.array([3, 1, 2]), transforms, np.ones(3, bool))
    assert shares[0] > 0.9  # A onto B: A's twin is where A stands
    assert shares[1] == 0.0  # the identity is not tested
    assert shares[2] < 0.05  # the car's old place holds its own next points only
    nothing_asked = _twin_shares(dst, stats, clouds, np.array([3, 1, 2]), transforms, np.zeros(3, bool))
    assert nothing_asked.max() == 0.0
    assert ICPFlowConfig.preset("waymo").checks.max_twin_share == 0.5
    assert ICPFlowConfig().checks.max_twin_share == 1.0  # off by default: stored configs load as made
