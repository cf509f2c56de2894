"""Schema validation of FramePair / FrameSequence and the flow conventions of icpflow.core.geometry."""

import numpy as np
import pytest

from icpflow.core.frame_pair import FramePair, FramePairError, FrameSequence
from icpflow.core.geometry import (
    ego_flow,
    euler_angles,
    full_to_residual,
    invert,
    is_rigid,
    kabsch,
    make_transform,
    orthonormalized,
    pose_error,
    relative_transform,
    residual_to_full,
    transform_points,
)


def _points(n, seed=0):
    return np.random.default_rng(seed).uniform(-20, 20, (n, 3)).astype(np.float32)


def _pair(**changes):
    fields = dict(pc0=_points(50), pc1=_points(60, 1), ego1_from_ego0=make_transform(0.1, (1.0, 0.2, 0.0)))
    fields.update(changes)
    return FramePair(**fields, source="test.npz")


def test_valid_pair_with_everything():
    n0 = 50
    pair = _pair(
        ground0=np.zeros(n0, bool),
        ground1=np.zeros(60, bool),
        flow=np.zeros((n0, 3), np.float32),
        flow_valid=np.ones(n0, bool),
        classes=np.zeros(n0, np.int32),
        instance=np.zeros(n0, np.int32),
        dynamic=np.zeros(n0, bool),
        time0=np.linspace(0, 0.1, n0, dtype=np.float32),
        time1=np.zeros(60, np.float32),
    )
    assert pair.has_ground_truth
    assert pair.time0[-1] == pytest.approx(0.1)
    assert set(pair.arrays()) >= {"pc0", "pc1", "flow", "ego1_from_ego0", "classes"}


BAD_CASES = [
    (dict(pc0=_points(5).astype(np.float64)), "pc0 must be float32"),
    (dict(pc0=np.zeros((5, 4), np.float32)), r"pc0 must have shape \(N, 3\)"),
    (dict(pc1=np.zeros(5, np.float32)), r"pc1 must have shape \(N, 3\)"),
    (dict(pc0=[[0.0, 0.0, 0.0]]), "pc0 must be a numpy array"),
    (dict(pc0=np.array([[0, 0, np.nan], [1, 1, 1]], np.float32)), "pc0 has 1 rows with NaN or Inf"),
    (dict(pc1=np.array([[0, np.inf, 0]], np.float32)), "pc1 has 1 rows with NaN or Inf"),
    (dict(ego1_from_ego0=np.eye(4, dtype=np.float32)), "ego1_from_ego0 must be float64"),
    (dict(ego1_from_ego0=np.eye(3)), r"must have shape \(4, 4\)"),
    (dict(ego1_from_ego0=np.diag([2.0, 1.0, 1.0, 1.0])), "is not rigid"),
    (dict(ego1_from_ego0=np.diag([-1.0, 1.0, 1.0, 1.0])), "is not rigid"),
    (dict(ego1_from_ego0=np.full((4, 4), np.nan)), "non-finite"),
    (dict(ground0=np.zeros(49, bool)), r"ground0 must have shape \(50,\)"),
    (dict(ground1=np.zeros(60, np.int32)), "ground1 must be bool"),
    (dict(flow=np.zeros((49, 3), np.float32)), r"flow must have shape \(50, 3\)"),
    (dict(flow=np.zeros((50, 3), np.float64)), "flow must be float32"),
    (dict(flow=np.full((50, 3), np.nan, np.float32)), "flow has NaN or Inf"),
    (dict(flow_valid=np.ones(50, np.uint8)), "flow_valid must be bool"),
    (dict(classes=np.zeros(50, np.int64)), "classes must be int32"),
    (dict(instance=np.zeros(51, np.int32)), r"instance must have shape \(50,\)"),
    (dict(dynamic=np.zeros(50, np.float32)), "dynamic must be bool"),
    (dict(time0=np.zeros(49, np.float32)), r"time0 must have shape \(50,\)"),
    (dict(time1=np.zeros(60, np.float64)), "time1 must be float32"),
    (dict(time0=np.full(50, np.nan, np.float32)), "time0 has NaN or Inf"),
    (dict(dt=0.0), "dt must be a positive"),
    (dict(dt=float("nan")), "dt must be a positive"),
    (dict(pose0=np.eye(4)), "pose0 and pose1 must be given together"),
    (dict(pose0=np.eye(4), pose1=make_transform(0.3, (5, 0, 0))), "disagrees with inv"),
]


@pytest.mark.parametrize("changes, message", BAD_CASES, ids=[m for _, m in BAD_CASES])
def test_bad_pairs_raise_one_line_naming_the_source(changes, message):
    with pytest.raises(FramePairError, match=message) as error:
        _pair(**changes)
    text = str(error.value)
    assert text.startswith("test.npz: ")
    assert "\n" not in text


def test_poses_give_ego_transform():
    pose0 = make_transform(0.3, (10.0, 5.0, 0.1))
    pose1 = make_transform(0.35, (11.0, 5.5, 0.1))
    pair = FramePair(pc0=_points(10), pc1=_points(10), pose0=pose0, pose1=pose1)
    np.testing.assert_allclose(pair.ego1_from_ego0, invert(pose1) @ pose0)
    # a static world point seen from both poses
    world = np.array([[3.0, -2.0, 1.0]])
    p0 = transform_points(invert(pose0), world)
    p1 = transform_points(invert(pose1), world)
    np.testing.assert_allclose(transform_points(pair.ego1_from_ego0, p0), p1, atol=1e-9)


def test_empty_scans_are_valid():
    pair = FramePair(pc0=np.zeros((0, 3), np.float32), pc1=np.zeros((0, 3), np.float32))
    assert pair.pc0.shape == (0, 3)


def test_full_residual_round_trip():
    rng = np.random.default_rng(3)
    pc0 = _points(1000, 4)
    transform = make_transform(0.05, (1.2, -0.3, 0.02), roll=0.01, pitch=-0.02)
    residual = rng.normal(0, 1, (1000, 3)).astype(np.float32)
    full = residual_to_full(residual, pc0, transform)
    np.testing.assert_allclose(full_to_residual(full, pc0, transform), residual, atol=1e-5)
    # static points: full flow is exactly the ego flow and the residual is zero
    static_full = transform_points(transform, pc0.astype(np.float64)) - pc0
    np.testing.assert_allclose(ego_flow(pc0, transform), static_full, atol=1e-5)
    np.testing.assert_allclose(full_to_residual(static_full.astype(np.float32), pc0, transform), 0, atol=1e-5)


def test_pair_helpers_follow_the_convention():
    transform = make_transform(0.2, (2.0, 1.0, 0.0))
    pc0 = _points(100)
    flow = ego_flow(pc0, transform) + np.float32([1.0, 0.0, 0.0])
    pair = FramePair(pc0=pc0, pc1=_points(5), ego1_from_ego0=transform, flow=flow)
    np.testing.assert_allclose(pair.residual_flow(), np.tile([1.0, 0.0, 0.0], (100, 1)), atol=1e-5)
    np.testing.assert_allclose(pair.pc0_in_frame1(), pc0 + pair.ego_flow(), atol=1e-4)
    with pytest.raises(FramePairError, match="no ego1_from_ego0"):
        FramePair(pc0=pc0, pc1=pc0).ego_flow()


def test_transform_helpers():
    transform = make_transform(0.7, (1.0, 2.0, 3.0), roll=0.1, pitch=-0.2)
    assert is_rigid(transform)
    np.testing.assert_allclose(invert(transform) @ transform, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(euler_angles(transform), (0.1, -0.2, 0.7), atol=1e-12)
    np.testing.assert_allclose(relative_transform(transform, transform), np.eye(4), atol=1e-12)
    # an estimate 0.3 m off along the truth's own x axis and turned 2 degrees about its z axis
    estimate = transform @ make_transform(np.radians(2.0), (0.3, 0.0, 0.0))
    np.testing.assert_allclose(pose_error(estimate, transform), (0.3, 2.0), atol=1e-9)
    assert pose_error(transform, transform) == pytest.approx((0.0, 0.0), abs=1e-5)


def _sequence():
    """Three scans; ego drives +1 m in x per scan; instance 1 moves +2 m in y per scan in the world."""
    poses = np.stack([make_transform(0.0, (float(t), 0.0, 0.0)) for t in range(3)])
    objects = {1: np.stack([make_transform(0.1 * t, (10.0, 2.0 * t, 0.0)) for t in range(3)])}
    points = [_points(40, t) for t in range(3)]
    instance = [np.r_[np.ones(10, np.int32), np.zeros(30, np.int32)] for _ in range(3)]
    return FrameSequence(
        points=points,
        poses=poses,
        timestamps_ns=np.arange(3, dtype=np.int64) * 100_000_000,
        instance=instance,
        classes=[i.copy() for i in instance],
        object_poses=objects,
        log_id="toy",
    )


def test_sequence_pairs_have_exact_flow():
    sequence = _sequence()
    for k in (1, 2):
        pair = sequence.pair(0, k)
        assert pair.dt == pytest.approx(0.1 * k)
        np.testing.assert_allclose(pair.ego1_from_ego0[:3, 3], (-k, 0, 0), atol=1e-12)
        static = pair.instance == 0
        np.testing.assert_allclose(pair.flow[static], pair.ego_flow()[static], atol=1e-5)
        moving = transform_points(pair.pose0, pair.pc0[~static].astype(np.float64))
        obj = sequence.object_poses[1]
        expected_world = transform_points(obj[k] @ invert(obj[0]), moving)
        np.testing.assert_allclose(
            pair.pc0[~static] + pair.flow[~static], transform_points(invert(pair.pose1), expected_world), atol=1e-4
        )
        assert pair.dynamic[~static].all() and not pair.dynamic[static].any()
    with pytest.raises(IndexError):
        sequence.pair(1, 2)


def test_sequence_validation_names_the_source():
    with pytest.raises(FramePairError, match=r"^seq: 2 scans need poses"):
        FrameSequence(points=[_points(3)] * 2, poses=np.stack([np.eye(4)]), timestamps_ns=np.zeros(2), source="seq")


def test_kabsch_recovers_a_rigid_motion_and_never_a_reflection():
    rng = np.random.default_rng(4)
    points = rng.normal(size=(50, 3)) * [4.0, 1.0, 0.5]
    truth = make_transform(0.3, (1.0, -2.0, 0.2), roll=0.05, pitch=-0.02)
    np.testing.assert_allclose(kabsch(points, transform_points(truth, points)), truth, atol=1e-9)
    mirrored = points * [1.0, 1.0, -1.0]  # the best fit of a mirror image is still a rotation
    fit = kabsch(points, mirrored)
    assert is_rigid(fit) and np.linalg.det(fit[:3, :3]) > 0


def test_orthonormalized_is_the_nearest_rigid_transform():
    """A product of rigid transforms drifts from orthonormal by rounding; ``orthonormalized`` puts it back (to the
    float64 precision) and keeps a rigid transform as it is; a perturbed rotation goes to its nearest rotation
    (det +1), the translation kept."""
    truth = make_transform(0.3, (1.0, -2.0, 0.2), roll=0.05, pitch=-0.02)
    drifted = np.eye(4)
    for _ in range(1000):
        drifted = drifted @ truth @ invert(truth)
    clean = orthonormalized(drifted)
    assert np.abs(clean[:3, :3] @ clean[:3, :3].T - np.eye(3)).max() < 1e-15
    np.testing.assert_allclose(orthonormalized(truth), truth, atol=1e-15)
    noisy = truth.copy()
    noisy[:3, :3] += np.random.default_rng(0).normal(0, 1e-3, (3, 3))
    fixed = orthonormalized(noisy)
    assert is_rigid(fixed) and np.linalg.det(fixed[:3, :3]) > 0
    np.testing.assert_array_equal(fixed[:3, 3], truth[:3, 3])
    assert np.abs(fixed - truth).max() < 3e-3  # the nearest rotation: within the noise of the true one


def test_lengths_are_numpys_norms_bit_for_bit():
    # the refinement's speeds: np.linalg.norm(axis=1)'s squares summed in its order, so the same floats (summing y + z
    # first differs on about a tenth of random rows: the test can tell)
    from icpflow.core.geometry import lengths

    rng = np.random.default_rng(0)
    for dtype in (np.float32, np.float64):
        vectors = (rng.normal(size=(200_000, 3)) * rng.uniform(1e-3, 1e3, (200_000, 1))).astype(dtype)
        vectors[:3] = [[np.inf, 0, 0], [np.nan, 1, 1], [0, 0, 0]]
        got = lengths(vectors)
        assert got.dtype == dtype and got.shape == (len(vectors),)
        np.testing.assert_array_equal(got, np.linalg.norm(vectors, axis=1))
        other = np.sqrt(vectors[:, 0] ** 2 + (vectors[:, 1] ** 2 + vectors[:, 2] ** 2))
        assert (other[3:] != got[3:]).mean() > 0.05
