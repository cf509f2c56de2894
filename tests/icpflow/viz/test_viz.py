"""icpflow.viz.pictures: the BEV picture and the open3d render show the points where they are, in their colours.

One hand-made pair: a dense 1 m cube of points at (10, 10) m moves 5 m along x in the world while the ego drives
2 m forward, so in the ego frame of t + dt pc0 (ego-compensated) sits at x = 8, pc1 at x = 13, and the full
ground-truth flow is (3, 0, 0) m.
"""

import matplotlib.image
import numpy as np
import pytest

from icpflow.core.frame_pair import FramePair
from icpflow.core.geometry import make_transform
from icpflow.viz.pictures import (
    MOVED_COLOUR,
    PC0_COLOUR,
    PC1_COLOUR,
    flow_colours,
    offscreen_problem,
    plot_bev,
    render_pair,
)

EXTENT = 20.0


@pytest.fixture(scope="module")
def pair():
    rng = np.random.default_rng(0)
    pc0 = (rng.random((3000, 3)) + [9.5, 9.5, 0.0]).astype(np.float32)
    ego1_from_ego0 = make_transform(translation=(-2.0, 0.0, 0.0))
    flow = np.tile(np.float32([3.0, 0.0, 0.0]), (len(pc0), 1))
    return FramePair(pc0=pc0, pc1=pc0 + flow, ego1_from_ego0=ego1_from_ego0, flow=flow, dt=0.1, sample_id="cube")


def centre_of(
    pixels: np.ndarray, colour, tolerance: float = 0.06, least: int = 20, near=None, radius: float = 0.0
) -> np.ndarray:
    """(row, column) mean of the pixels of (H, W, 3+) float image ``pixels`` within ``tolerance`` of ``colour``
    (only those within ``radius`` pixels of (row, column) ``near`` if given)."""
    match = np.all(np.abs(pixels[..., :3] - np.asarray(colour)) < tolerance, axis=-1)
    if near is not None:
        grid_rows, grid_cols = np.indices(match.shape)
        match &= np.hypot(grid_rows - near[0], grid_cols - near[1]) < radius
    rows, cols = np.nonzero(match)
    assert len(rows) >= least, f"{len(rows)} pixels of colour {colour}"
    return np.array([rows.mean(), cols.mean()])


def metres_of(panel: np.ndarray, colour, near=None, tolerance: float = 0.06) -> np.ndarray:
    """(x, y) metres of the mean pixel of ``colour`` in one BEV ``panel`` (H, W, 3+), mapped through its axes box
    (the black spines, limits +-EXTENT); ``near`` (x, y): only pixels within 2 m of it."""
    dark = np.all(panel[..., :3] < 0.3, axis=-1)
    spine_rows, spine_cols = np.flatnonzero(dark.mean(axis=1) > 0.5), np.flatnonzero(dark.mean(axis=0) > 0.5)
    top, left, right = spine_rows.min(), spine_cols.min(), spine_cols.max()
    pixels_per_metre = (right - left) / (2 * EXTENT)
    near_pixel = (
        None
        if near is None
        else (top + (EXTENT - near[1]) * pixels_per_metre, left + (near[0] + EXTENT) * pixels_per_metre)
    )
    row, col = centre_of(panel, colour, tolerance, near=near_pixel, radius=2 * pixels_per_metre)
    return np.array([-EXTENT + (col - left) / pixels_per_metre, EXTENT - (row - top) / pixels_per_metre])


def test_bev_panels_show_the_points_where_they_are(pair, tmp_path):
    ego_only = np.tile(np.float32([-2.0, 0.0, 0.0]), (len(pair.pc0), 1))  # predicted: nothing moves in the world
    path = plot_bev(pair, tmp_path / "bev.png", predicted=ego_only, extent=EXTENT)
    image = matplotlib.image.imread(path)
    height, width = image.shape[:2]  # 2 x 3 panels: pc0/pc1, predicted, its residual; ground truth, its residual

    def panel(row, col):
        return image[row * height // 2 : (row + 1) * height // 2, col * width // 3 : (col + 1) * width // 3]

    pc0_at, pc1_at = (8.0, 10.0), (13.0, 10.0)  # cube centres (m) in the ego frame of t + dt

    np.testing.assert_allclose(metres_of(panel(0, 0), PC0_COLOUR), pc0_at, atol=0.3)
    np.testing.assert_allclose(metres_of(panel(0, 0), PC1_COLOUR), pc1_at, atol=0.3)
    # pc0 + predicted (ego-only) flow: on pc0, pc1 where it is
    np.testing.assert_allclose(metres_of(panel(0, 1), MOVED_COLOUR), pc0_at, atol=0.3)
    np.testing.assert_allclose(metres_of(panel(0, 1), PC1_COLOUR), pc1_at, atol=0.3)
    # its residual flow is zero: grey (as anti-aliased text can be, hence looked for near pc0)
    np.testing.assert_allclose(metres_of(panel(0, 2), (0.6, 0.6, 0.6), near=pc0_at, tolerance=0.02), pc0_at, atol=0.3)
    # pc0 + ground-truth flow lands on pc1; its residual (5 m in 0.1 s along +x) in full colour at pc0
    np.testing.assert_allclose(metres_of(panel(1, 0), MOVED_COLOUR), pc1_at, atol=0.3)
    residual_colour = flow_colours(np.float32([[5.0, 0.0, 0.0]]), 0.1)[0]
    np.testing.assert_allclose(metres_of(panel(1, 1), residual_colour), pc0_at, atol=0.3)


@pytest.fixture(scope="module")
def renderable():
    problem = offscreen_problem()
    if problem:
        pytest.skip(problem)


def test_render_shows_pc0_pc1_and_moved_points(pair, tmp_path, renderable):
    half = pair.flow / 2  # pc0 + flow lands half-way between pc0 and pc1
    path = render_pair(pair, tmp_path / "render.png", predicted=half, size=(320, 240), extent=EXTENT)
    image = matplotlib.image.imread(path)
    assert image.shape[:2] == (240, 320)
    assert np.mean(np.all(image[..., :3] == 1.0, axis=-1)) > 0.5  # white background
    rows = [centre_of(image, colour, tolerance=0.02)[0] for colour in (PC0_COLOUR, MOVED_COLOUR, PC1_COLOUR)]
    # seen from behind the ego vehicle, points further ahead (x 8, 10.5, 13 m) are higher up in the picture
    assert rows[0] > rows[1] > rows[2], rows


def test_render_without_any_flow_draws_two_clouds(pair, tmp_path, renderable):
    path = render_pair(pair.replace(flow=None), tmp_path / "render.png", size=(160, 120), extent=EXTENT)
    image = matplotlib.image.imread(path)
    assert image.shape[:2] == (120, 160)
    centre_of(image, PC0_COLOUR, tolerance=0.02)
    centre_of(image, PC1_COLOUR, tolerance=0.02)
    assert not np.any(np.all(np.abs(image[..., :3] - np.asarray(MOVED_COLOUR)) < 0.02, axis=-1))
