"""icpflow.scans.bev: the bird's-eye-view cells of a cloud, against the numpy expressions they replace (the same cells,
bit for bit, also for points on a cell's edge)."""

import numpy as np
import pytest

from icpflow.scans.bev import in_box_cells, occupied_cells


def edge_points(rng, count, dtype):
    """Random points, a third of them exactly on a 0.5 m cell's edge and a third a rounding step off it."""
    points = rng.uniform(-30, 30, (count, 3))
    third = count // 3
    points[:third, :2] = np.round(points[:third, :2] * 2) / 2
    points = points.astype(dtype)
    points[third : 2 * third, :2] = np.nextafter(np.round(points[third : 2 * third, :2] * 2) / 2, 0).astype(dtype)
    return points


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_occupied_cells_are_numpys_floor(dtype):
    rng = np.random.default_rng(0)
    points = edge_points(rng, 6000, dtype)
    occupying = rng.random(len(points)) < 0.5
    for cell in (0.5, 0.3, 1.0):
        cells, occupied = occupied_cells(points, points.dtype.type(cell), occupying)
        expected = np.floor(points[:, :2] / cell).astype(np.int64)  # numpy: the points' precision
        expected -= expected.min(axis=0)
        grid = np.zeros(tuple(expected.max(axis=0) + 1), bool)
        grid[expected[occupying, 0], expected[occupying, 1]] = True
        assert np.array_equal(cells, expected) and np.array_equal(occupied, grid)


def test_in_box_cells_are_the_points_of_the_cells_the_boxes_touch():
    rng = np.random.default_rng(1)
    points = edge_points(rng, 20000, np.float32)
    lows = np.round(rng.uniform(-30, 25, (15, 3)) * 2) / 2  # box corners on cell edges too
    highs = lows + rng.uniform(0.0, 6, (15, 3))
    for cell in (0.5, 0.7):
        origin = lows[:, :2].min(axis=0)
        first = np.floor((lows[:, :2] - origin) / cell).astype(np.int64)
        last = np.floor((highs[:, :2] - origin) / cell).astype(np.int64)
        covered = np.zeros(tuple(last.max(axis=0) + 1), bool)
        for (x0, y0), (x1, y1) in zip(first, last):
            covered[x0 : x1 + 1, y0 : y1 + 1] = True
        cells = np.floor((points[:, :2] - origin) / cell)
        near = np.flatnonzero(np.all((cells >= 0) & (cells < covered.shape), axis=1))
        expected = near[covered[cells[near, 0].astype(np.int64), cells[near, 1].astype(np.int64)]]
        found = in_box_cells(points, lows, highs, cell)
        assert len(expected) > 500 and np.array_equal(found, expected)
