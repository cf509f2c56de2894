"""``icpflow.teacher.hdbscan_labels`` against the hdbscan package it replaces in the teacher's clustering step: on
the package's own spanning trees the same hierarchy and labels, exactly; from points the same labels, point for
point, on blobs with noise, a synthetic scene and (the av2 preset's settings) a real AV2 sweep, and all but a few
points where neighbours tie in distance (the real sweep at other settings, a lattice with duplicates)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from icpflow.datasets.file_formats import read_feather
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.teacher.clustering import voxel_downsample
from icpflow.teacher.hdbscan_labels import hdbscan_labels, labels_from_spanning_tree, single_linkage

from helpers.data import require_shared

SETTINGS = [  # (min_cluster_size, min_samples, epsilon): the presets' (av2, waymo) and others
    (20, 20, 0.25),
    (30, 30, 0.25),
    (10, 5, 0.0),
    (5, 3, 1.0),
]


def package_labels(points, min_cluster_size, min_samples, epsilon):
    import hdbscan

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return hdbscan.HDBSCAN(
            min_cluster_size=min_cluster_size,
            min_samples=min_samples,
            cluster_selection_epsilon=epsilon,
            algorithm="boruvka_kdtree",
            approx_min_span_tree=True,
            leaf_size=100,
            core_dist_n_jobs=1,
        ).fit_predict(points)


def blobs(seed: int) -> np.ndarray:
    """12 Gaussian blobs of 30-400 points (spread 0.2-1 m) in a 60 m box and 500 uniform noise points."""
    rng = np.random.default_rng(seed)
    centres = np.column_stack([rng.uniform(-30, 30, (12, 2)), rng.uniform(0, 2, 12)])
    parts = [c + rng.normal(0, rng.uniform(0.2, 1.0), (int(rng.integers(30, 400)), 3)) for c in centres]
    return np.concatenate([*parts, rng.uniform(-30, 30, (500, 3))])


def synthetic_scene() -> np.ndarray:
    """The non-ground points of a synthetic pair's two scans, fused, on 0.1 m voxels (what the teacher clusters)."""
    pair = SyntheticDataset(split="val", num_sequences=1, frames_per_sequence=2).pair(0)
    fused = np.concatenate([pair.pc0[~pair.ground0], pair.pc1[~pair.ground1]])
    return voxel_downsample(fused, 0.1)[0].astype(np.float64)


def av2_sweep() -> np.ndarray:
    """One real AV2 sweep above 0.3 m within 51.2 m, on the av2 preset's 0.25 m voxels (about 25k points)."""
    logs = require_shared("av2", "sensor", "val", what="the real Argoverse 2 sweeps", glob="*/sensors/lidar/*.feather")
    sweeps = sorted(logs.glob("*/sensors/lidar/*.feather"))
    points = read_feather(sweeps[0], ("x", "y", "z"))[["x", "y", "z"]].to_numpy().astype(np.float32)
    keep = (points[:, 2] > 0.3) & (np.abs(points[:, :2]).max(axis=1) < 51.2)
    return voxel_downsample(points[keep], 0.25)[0].astype(np.float64)


POINT_SETS = {
    "blobs": lambda: np.concatenate([blobs(0), blobs(1) + 70.0]),
    "synthetic": synthetic_scene,
    "av2": av2_sweep,
}


@pytest.mark.parametrize("source", list(POINT_SETS))
def test_the_package_s_spanning_tree_gives_its_hierarchy_and_labels(source):
    from hdbscan.hdbscan_ import _hdbscan_boruvka_kdtree, _tree_to_labels

    points = POINT_SETS[source]()
    for min_cluster_size, min_samples, epsilon in SETTINGS:
        hierarchy, tree = _hdbscan_boruvka_kdtree(
            points, min_samples, metric="euclidean", leaf_size=100, core_dist_n_jobs=1, gen_min_span_tree=True
        )
        np.testing.assert_array_equal(single_linkage(tree), hierarchy)
        theirs = _tree_to_labels(points, hierarchy, min_cluster_size, cluster_selection_epsilon=epsilon)[0]
        ours = labels_from_spanning_tree(tree, min_cluster_size, epsilon)
        assert ours.max() >= 1, "a case with clusters to compare"
        np.testing.assert_array_equal(ours, theirs, err_msg=f"{source} {min_cluster_size, min_samples, epsilon}")


@pytest.mark.parametrize("source", ["blobs", "synthetic"])
def test_the_same_labels_as_the_package(source):
    points = POINT_SETS[source]()
    for setting in SETTINGS:
        ours = hdbscan_labels(points, *setting, leaf_size=100, workers=2)
        np.testing.assert_array_equal(ours, package_labels(points, *setting), err_msg=f"{source} {setting}")


def moved(ours: np.ndarray, theirs: np.ndarray) -> int:
    """Points outside the best overlap of each of our clusters (noise included) with one of theirs."""
    kept = sum(np.bincount(theirs[ours == k] + 1).max() for k in np.unique(ours))
    return len(ours) - kept


def test_real_sweep_same_labels_at_the_av2_preset_and_nearly_elsewhere():
    points = av2_sweep()
    for setting in SETTINGS:
        ours, theirs = hdbscan_labels(points, *setting, leaf_size=100, workers=2), package_labels(points, *setting)
        if setting == (20, 20, 0.25):
            np.testing.assert_array_equal(ours, theirs)
        assert abs(int(ours.max()) - int(theirs.max())) <= 2
        assert moved(ours, theirs) <= 0.005 * len(points), setting  # (10, 5, 0): 38 of 21,817 (ties in distance)


def test_ties_and_duplicates_move_few_points():
    """Points on a 0.1 m lattice with 200 exact duplicates: distances tie everywhere, so which of two tied
    neighbours comes first (scipy vs scikit-learn) may change the approximate spanning tree."""
    rng = np.random.default_rng(3)
    for _ in range(3):
        points = np.concatenate([c + rng.normal(0, 0.3, (100, 3)) for c in rng.uniform(-10, 10, (6, 3))])
        points = np.round(np.concatenate([points, points[rng.integers(0, len(points), 200)]]), 1)
        for setting in [(20, 20, 0.25), (5, 3, 0.5)]:
            ours, theirs = hdbscan_labels(points, *setting, leaf_size=100, workers=1), package_labels(points, *setting)
            assert ours.max() == theirs.max() == 5
            assert moved(ours, theirs) <= 0.01 * len(points)


def test_no_cluster_when_every_group_is_too_small():
    points = np.random.default_rng(0).normal(0, 1, (25, 3))
    assert (hdbscan_labels(points, 30, 10, 0.25, leaf_size=100, workers=1) == -1).all()
