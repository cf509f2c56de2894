"""The Predictor's ICP refinement (``fastflow3d.inference.refine``) on synthetic pairs with exact flow: it recovers
motion that a student under-predicts, leaves what it cannot improve, and the Predictor runs it on request only."""

import numpy as np
import pytest

from fastflow3d.inference.refine import RefineConfig, components, median_at_least, refine_residual
from icpflow.core.geometry import ego_flow, transform_points
from icpflow.datasets.synthetic.reader import SyntheticDataset


@pytest.fixture(scope="module")
def network_view():
    """What the network of a pair sees, with the truth: (pc0 compensated (N, 3), pc1 (M, 3), true residual (N, 3),
    moving (N,) bool) of the non-ground points inside +-32 m of two synthetic pairs."""
    dataset = SyntheticDataset(split="test", num_sequences=2, frames_per_sequence=2, seed=3)
    views = []
    for index in range(len(dataset)):
        pair = dataset[index]
        keep0 = ~pair.ground0
        compensated = transform_points(pair.ego1_from_ego0, pair.pc0)[keep0].astype(np.float32)
        residual = (pair.flow - ego_flow(pair.pc0, pair.ego1_from_ego0))[keep0].astype(np.float32)
        inside = np.all(np.abs(compensated[:, :2]) < 32.0, axis=1)
        moving = np.linalg.norm(residual, axis=1) / pair.dt > 0.5
        views.append((compensated[inside], pair.pc1[~pair.ground1], residual[inside], moving[inside]))
    return views


def epe(flow, truth, mask):
    return float(np.linalg.norm(flow - truth, axis=1)[mask].mean())


def test_components_are_eight_connected_cells():
    points = np.array([[0.1, 0.1, 0], [0.6, 0.6, 0], [1.1, 1.1, 0.0], [3.0, 3.0, 0], [3.2, 3.1, 5.0]], np.float32)
    label, count = components(points, 0.5)
    assert count == 2 and len(set(label[:3])) == 1 and label[3] == label[4] != label[0]
    assert components(np.zeros((0, 3), np.float32), 0.5)[1] == 0


def test_refinement_recovers_the_motion_a_student_under_predicts(network_view):
    for pc0, pc1, truth, moving in network_view:
        student = (0.6 * truth).astype(np.float32)  # the right direction, 60 % of the motion
        refined, replaced = refine_residual(pc0, student, pc1, RefineConfig())
        assert refined.dtype == np.float32 and refined.shape == pc0.shape
        # objects predicted faster than static_max_motion: nearly all registered, and far better
        fast = moving & (np.linalg.norm(student, axis=1) > RefineConfig().static_max_motion)
        assert fast.sum() > 1000 and replaced[fast].mean() > 0.9
        assert epe(refined, truth, fast) < 0.4 * epe(student, truth, fast)
        # slower ones may be judged static (the teacher's static tolerance): never much worse than the student
        assert epe(refined, truth, moving) < epe(student, truth, moving)
        # what the student calls static is left exactly as it is
        assert np.array_equal(refined[~moving], student[~moving]) and not replaced[~moving].any()


def test_refinement_keeps_a_right_student_and_pulls_back_a_wrong_one(network_view):
    pc0, pc1, truth, moving = network_view[0]
    refined, _ = refine_residual(pc0, truth, pc1, RefineConfig())
    assert epe(refined, truth, moving) < 0.05  # an exact student stays (nearly) exact
    # a student that moves static objects (0.6 m along x) is corrected, not followed: objects the refinement takes
    # (components of at most max_extent) without a moving point
    label, count = components(pc0, 0.5)
    sizes = [np.ptp(pc0[label == k, :2], axis=0) for k in range(count)]
    small = np.flatnonzero([np.linalg.norm(size) <= RefineConfig().max_extent for size in sizes])
    static_objects = np.isin(label, small) & np.isin(label, np.unique(label[moving]), invert=True)
    assert static_objects.sum() > 1000
    wrong = truth.copy()
    wrong[static_objects] += np.float32([0.6, 0.0, 0.0])
    refined, replaced = refine_residual(pc0, wrong, pc1, RefineConfig())
    assert replaced[static_objects].any()
    assert epe(refined, truth, static_objects) < 0.5 * epe(wrong, truth, static_objects)
    # moved a little (0.2 m), static objects that no motion fits nearly as well get exactly none (the teacher's
    # static tolerance); without the tolerance ICP's small slides remain
    wrong = truth.copy()
    wrong[static_objects] += np.float32([0.2, 0.0, 0.0])
    refined, replaced = refine_residual(pc0, wrong, pc1, RefineConfig())
    zero = replaced & static_objects & np.all(refined == 0, axis=1)
    assert zero.sum() > 0.5 * static_objects.sum()
    refined, replaced = refine_residual(pc0, wrong, pc1, RefineConfig(static_tolerance=0.0))
    assert not np.any(replaced & static_objects & np.all(refined == 0, axis=1))


def test_refinement_settings_are_checked():
    assert RefineConfig.of(None) is None and RefineConfig.of(False) is None
    assert RefineConfig.of(True) == RefineConfig()
    assert RefineConfig.of({"max_corr": [0.5, 0.1]}).max_corr == (0.5, 0.1)
    with pytest.raises(ValueError, match="unknown settings"):
        RefineConfig.of({"cells": 0.5})
    with pytest.raises(ValueError, match="invalid cell, max_corr"):
        RefineConfig(cell=0.0, max_corr=())
    with pytest.raises(ValueError, match="refine must be"):
        RefineConfig.of("yes")
    # a wrong type names its field, never a bare conversion error
    for given, message in [
        ({"max_corr": "abc"}, "max_corr must be a list of metres"),
        ({"max_corr": 0.5}, "max_corr must be a list of metres"),
        ({"cell": "x"}, "cell must be a number"),
        ({"min_points": 12.5}, "min_points must be an integer"),
        ({"max_iter": True}, "max_iter must be an integer"),
    ]:
        with pytest.raises(ValueError, match=message):
            RefineConfig.of(given)
    assert RefineConfig.of({"min_points": 12.0, "cell": 1}) == RefineConfig(min_points=12, cell=1.0)


def test_refinement_of_degenerate_scans():
    xy = np.stack(np.meshgrid(np.arange(-20.0, 20.0, 0.25), np.arange(-20.0, 20.0, 0.25)), -1).reshape(-1, 2)
    flat = np.column_stack([xy, np.zeros(len(xy))]).astype(np.float32)  # one 40 m component
    for pc0, pc1 in [
        (np.zeros((1, 3), np.float32), np.zeros((1, 3), np.float32)),  # one point
        (flat, flat + np.float32([0.3, 0.0, 0.0])),  # one component longer than max_extent
        (np.zeros((0, 3), np.float32), flat),  # nothing in pc0
    ]:
        residual = np.full(pc0.shape, 0.3, np.float32)
        refined, replaced = refine_residual(pc0, residual, pc1, RefineConfig())
        assert np.array_equal(refined, residual) and not replaced.any()
    # 500 identical points in both scans: whatever the student says, they did not move
    same = np.ones((500, 3), np.float32)
    refined, replaced = refine_residual(same, np.full((500, 3), 0.3, np.float32), same, RefineConfig())
    assert replaced.all() and np.abs(refined).max() < 1e-6


def test_an_accepted_motion_moves_only_the_points_it_fits():
    """A post that the occupancy grid joins to a passing bus (0.3 m apart: one component) keeps the student's
    flow; the bus gets its full motion (issue 44: the refinement must not make static points worse than the network
    alone). Where the student smears some of the bus's motion onto the post, the points that the bus's motion fits
    as well (within ``point_slack``) may take it: a few, never the post."""
    from helpers.teacher_scenes import box_surface  # tests/ is on sys.path (pytest's prepend import mode)

    rng = np.random.default_rng(0)
    # sparse enough to enter ICP whole (max_points): pc1 holds the very points of pc0, moved or not
    bus = box_surface((10.0, 2.5, 3.0), rng, spacing=0.5) + np.float64([5.0, 3.0, 0.2])
    parked = box_surface((0.6, 0.6, 1.5), rng, spacing=0.2) + np.float64([7.0, 1.15, 0.0])  # 0.3 m beside the bus
    motion = np.float64([1.5, 0.0, 0.0])
    pc0 = np.concatenate([bus, parked]).astype(np.float32)
    pc1 = np.concatenate([bus + motion, parked]).astype(np.float32)
    on_bus = np.arange(len(pc0)) < len(bus)
    assert components(pc0, RefineConfig().cell)[1] == 1
    truth = np.where(on_bus[:, None], motion, 0.0).astype(np.float32)
    for smear in (0.0, 0.2):
        student = np.where(on_bus[:, None], 0.6 * motion, smear * motion).astype(np.float32)
        refined, replaced = refine_residual(pc0, student, pc1, RefineConfig())
        assert replaced[on_bus].mean() > 0.9 and epe(refined, truth, on_bus) < 0.05
        if smear == 0:
            assert not replaced[~on_bus].any() and np.array_equal(refined[~on_bus], student[~on_bus])
        else:
            assert replaced[~on_bus].mean() < 0.1 and epe(refined, truth, ~on_bus) < 1.1 * epe(student, truth, ~on_bus)
        # without the per-point rule the post was carried along with the bus
        carried, _ = refine_residual(pc0, student, pc1, RefineConfig(point_slack=np.inf))
        assert epe(carried, truth, ~on_bus) > 1.0


def test_ground_surface_left_in_the_scans_joins_no_objects_and_stays_out_of_icp():
    """Estimated ground leaves a ring of surface points around objects (``GroundSegmenter.masks``' surface): a
    slow car and a parked one joined by such a strip are one component, which the identity fits about as well (the
    strip and the parked car do not move), so the moving car keeps the student's short flow. Told the scans'
    surfaces, the refinement builds objects from the points above them: the car is refined, the parked one and the
    strip keep the student's flow, and the car's own feet (surface points in its cells) move with it. Surfaces
    that hold nothing change nothing."""
    from helpers.teacher_scenes import box_surface  # tests/ is on sys.path (pytest's prepend import mode)

    rng = np.random.default_rng(1)
    car = box_surface((4.4, 1.8, 1.4), rng, spacing=0.2) + np.float64([4.0, 0.0, 0.2])
    feet = np.column_stack([rng.uniform(2.0, 6.0, 40), rng.uniform(-0.8, 0.8, 40), np.full(40, 0.1)])
    parked = box_surface((4.4, 1.8, 1.4), rng, spacing=0.2) + np.float64([4.0, 4.0, 0.2])
    # the strip lies between the cars, in cells of neither (the car's end at y = 0.9, the parked one's at 3.1)
    strip = np.column_stack([rng.uniform(1.0, 7.0, 600), rng.uniform(1.1, 2.9, 600), rng.uniform(0.0, 0.1, 600)])
    motion = np.float64([0.4, 0.0, 0.0])  # 4 m/s: within the static rule's reach (static_max_motion)
    pc0 = np.concatenate([car, feet, parked, strip]).astype(np.float32)
    pc1 = np.concatenate([car + motion, feet + motion, parked, strip]).astype(np.float32)
    sizes = np.cumsum([len(car), len(feet), len(parked), len(strip)])
    index = np.arange(len(pc0))
    on_car, on_feet, on_strip = index < sizes[0], (index >= sizes[0]) & (index < sizes[1]), index >= sizes[2]
    surface0, surface1 = on_feet | on_strip, on_feet | on_strip  # the same rows in both scans
    truth = np.where((on_car | on_feet)[:, None], motion, 0.0).astype(np.float32)
    student = np.where((on_car | on_feet)[:, None], 0.3 * motion, 0.0).astype(np.float32)
    cfg = RefineConfig()
    assert components(pc0, cfg.cell)[1] == 1 and components(pc0, cfg.cell, ~surface0)[1] == 2
    joined, joined_replaced = refine_residual(pc0, student, pc1, cfg)
    assert not joined_replaced[on_car].any() and epe(joined, truth, on_car) > 0.25
    refined, replaced = refine_residual(pc0, student, pc1, cfg, surface0, surface1)
    assert replaced[on_car].mean() > 0.9 and epe(refined, truth, on_car) < 0.03
    assert replaced[on_feet].mean() > 0.9 and epe(refined, truth, on_feet) < 0.03
    assert np.array_equal(refined[~(on_car | on_feet)], student[~(on_car | on_feet)])
    nothing = np.zeros(len(pc0), bool)
    same, same_replaced = refine_residual(pc0, student, pc1, cfg, nothing, nothing)
    assert np.array_equal(same, joined) and np.array_equal(same_replaced, joined_replaced)


def test_the_targets_are_searched_among_the_points_of_the_cells_the_boxes_touch():
    """icpflow.scans.bev.in_box_cells (the refinement's targets): every point inside a candidate's box is kept (so its
    targets, and their order along x, are those of the whole scan), and a point far from every box is not."""
    from icpflow.scans.bev import in_box_cells

    rng = np.random.default_rng(4)
    points = rng.uniform(-40, 40, (20000, 3)).astype(np.float32)
    lows = rng.uniform(-40, 30, (12, 3))
    highs = lows + rng.uniform(0.2, 8, (12, 3))
    lows[:2, 2], highs[:2, 2] = -50, 50  # two boxes of every height: many points inside
    kept = in_box_cells(points, lows, highs, 0.5)
    assert np.all(np.diff(kept) > 0)
    inside = np.zeros(len(points), bool)
    for low, high in zip(lows, highs):
        inside |= np.all((points >= low) & (points <= high), axis=1)
    assert inside.sum() > 100 and set(np.flatnonzero(inside)) <= set(kept)
    gap = np.full(len(points), np.inf)  # each point's distance to the nearest box in the bird's-eye view
    for low, high in zip(lows, highs):
        outside = np.maximum(np.maximum(low[:2] - points[:, :2], points[:, :2] - high[:2]), 0)
        gap = np.minimum(gap, np.linalg.norm(outside, axis=1))
    assert np.all(gap[kept] < 0.5 * np.sqrt(2) + 1e-6) and np.any(gap > 1.0)


def test_median_at_least_is_numpys_median_compared():
    """``median_at_least`` (the candidates' speed test, without a sort) says what ``numpy.median(segment) >=
    threshold`` says, for segments of odd and even size, of one value, with ties and values on the threshold."""
    rng = np.random.default_rng(3)
    for trial in range(200):
        sizes = rng.integers(1, 9, rng.integers(1, 30))
        ties = rng.choice([0.0, 0.04, 0.05, 0.06, 0.1], sizes.sum())  # equal values, values on the threshold
        values = ties if trial % 2 else rng.uniform(0, 0.1, sizes.sum())
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        for threshold in (0.05, 0.045, 0.0):
            expected = [np.median(values[a : a + n]) >= threshold for a, n in zip(starts, sizes)]
            assert median_at_least(values, starts, sizes, threshold).tolist() == expected
