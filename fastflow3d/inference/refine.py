"""The Predictor's opt-in refinement: the teacher's ICP started from the student's flow, per cheap object.

The student's flow is right in direction and often short in length (a bus moves by about half its motion: BENCHMARKS.md,
"Refinement"); the teacher's ICP is exact where it starts close enough. This stage joins them, per pair:

1. Objects: the 8-connected components of the bird's-eye-view occupancy (``RefineConfig.cell`` metres) of the
   network's pc0 points (ego-compensated, non-ground, inside the grid). Components with fewer than ``min_points``
   points or longer than ``max_extent`` (walls, kerbs, hedges) are left as they are. Where the scans' ground
   surfaces are known (an estimated ground leaves the ring the sensor draws around each object's foot:
   ``icpflow.scans.ground.GroundSegmenter.masks``), only the points above them occupy cells; a surface point joins the
   object in its cell (its feet) or none, and stays out of the ICP and its checks (steps 3, 4) on both scans: the
   ring would join moving objects to parked ones.
2. Candidates: components whose median predicted residual is at least ``min_motion`` metres per pair (the moving
   ones; the rest keep the student's flow).
3. Registration: the component's points are moved onto the pc1 points near them by point-to-point ICP (the
   teacher's kernel, ``icpflow.teacher.registration.icp``; yaw and 3D translation, ``yaw_only``) from the translation of
   the component's mean predicted residual, with correspondences truncated at each distance of ``max_corr`` in turn
   (coarse to fine: the student's start may be a metre short). The registration is the teacher's kernel run
   coarse to fine in one compiled call (``icpflow.teacher.registration.cpu.register_stages_cpu``, numba, parallel
   over the components), which also measures the match of no motion and of the student's own flow, on at most
   ``max_points`` points of each component.
4. Checks: the ICP motion replaces the student's flow of the component only when it passes the teacher's checks
   (``icpflow.teacher.checks.passes``: mean error below ``max_error``, IoU ratio at least ``min_iou``, no roll or
   pitch beyond 9 degrees), its match is better than the student's own (pc0 + predicted residual, measured the same
   way) and its motion lies within ``max_change`` metres of the student's at the component's centroid. As in the
   teacher (``icp.static_tolerance``), no motion replaces the ICP motion where it fits within ``static_tolerance``
   of its error, for components the student moves at most ``static_max_motion``: a student that moves a parked
   car a little is pulled back to zero, while a fast bus side (which slides along itself, so that no motion fits it
   nearly as well too) keeps its motion.
5. Points: an accepted motion replaces the student's flow only at the component's points it fits: a point whose
   nearest pc1 point (within the component's targets; exact, ``icpflow.scans.neighbours``) is farther after the
   ICP motion than after the student's own flow by more than ``point_slack`` keeps the student's flow. A parked
   car or a wall that the occupancy grid joins to a passing bus is not carried along with it, so the refinement
   leaves the static foreground no worse than the network alone.

Frames: every array is in the ego frame of t + dt (pc0 already compensated); flows are residual (ego-compensated)
flows in metres per pair, float32 in and out.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from icpflow.core.geometry import lengths, rigid_flow


@dataclass(frozen=True)
class RefineConfig:
    """Settings of the refinement (module docstring); ``RefineConfig()`` is the measured default."""

    cell: float = 0.5  # m: bird's-eye-view occupancy cell of the objects
    min_points: int = 10  # points of a component below which it keeps the student's flow
    max_extent: float = 20.0  # m: longer components (bounding-box diagonal) keep the student's flow
    min_motion: float = 0.05  # m per pair: components predicted slower keep the student's flow
    margin: float = 1.0  # m: pc1 points within the moved component's box grown by this are ICP's targets
    max_points: int = 500  # points of a component entering ICP and its checks (an even subsample of larger ones)
    max_corr: tuple[float, ...] = (2.0, 1.0, 0.3, 0.1)  # m: ICP truncation, coarse to fine
    max_iter: int = 40  # ICP iterations per truncation distance (at most)
    max_error: float = 0.2  # m: mean nearest-neighbour distance of an accepted registration
    min_iou: float = 0.1  # the teacher's IoU ratio (checks.passes) of an accepted registration, inliers at max_corr[-1]
    max_change: float = 2.0  # m: largest accepted difference from the student's motion at the centroid
    static_tolerance: float = 0.25  # no motion replaces the ICP motion where it fits within this fraction of its
    # error (the teacher's icp.static_tolerance: scans sample a static surface differently); 0 = off
    static_max_motion: float = 0.5  # m per pair: ... for components the student moves at most this far (a fast
    # flat side sliding along itself also fits no motion nearly as well)
    point_slack: float = 0.05  # m: a point keeps the student's flow where the accepted motion fits it worse than
    # that flow by more than this (step 5)

    def __post_init__(self):
        problems = [
            name
            for name, ok in (
                ("cell", self.cell > 0),
                ("min_points", self.min_points >= 3),
                ("max_points", self.max_points >= self.min_points),
                ("max_extent", self.max_extent > 0),
                ("min_motion", self.min_motion >= 0),
                ("margin", self.margin >= 0),
                ("max_corr", len(self.max_corr) > 0 and all(d > 0 for d in self.max_corr)),
                ("max_iter", self.max_iter >= 1),
                ("max_error", self.max_error > 0),
                ("min_iou", 0 <= self.min_iou <= 1),
                ("max_change", self.max_change > 0),
                ("static_tolerance", self.static_tolerance >= 0),
                ("static_max_motion", self.static_max_motion >= 0),
                ("point_slack", self.point_slack >= 0),
            )
            if not ok
        ]
        if problems:
            raise ValueError(f"refine: invalid {', '.join(problems)} in {asdict(self)}")

    @classmethod
    def of(cls, value) -> RefineConfig | None:
        """None (off) from None/False, the default from True, or a config from a dict of its fields."""
        if value is None or value is False:
            return None
        if value is True:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, dict):
            unknown = set(value) - set(cls.__dataclass_fields__)
            if unknown:
                raise ValueError(f"refine: unknown settings {sorted(unknown)}")
            return cls(
                **{name: _typed(name, given, cls.__dataclass_fields__[name].type) for name, given in value.items()}
            )
        raise ValueError(f"refine must be true, false or a dict of RefineConfig fields, got {value!r}")


def _typed(name: str, value, kind: str):
    """``value`` of a ``RefineConfig`` field as its type (``kind``: the annotation, ``float``, ``int`` or a tuple of
    floats); ValueError naming the field otherwise (bools and fractional counts are refused)."""
    if kind.startswith("tuple"):
        items = list(value) if isinstance(value, (list, tuple)) else None
        if items is None or not all(_is_number(item) for item in items):
            raise ValueError(f"refine: {name} must be a list of metres, got {value!r}")
        return tuple(float(item) for item in items)
    if not _is_number(value) or (kind == "int" and float(value) != int(value)):
        raise ValueError(f"refine: {name} must be {'an integer' if kind == 'int' else 'a number'}, got {value!r}")
    return int(value) if kind == "int" else float(value)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def components(points: np.ndarray, cell: float, occupying: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """((N,) int64 component of each (N, 3) point, number of components): 8-connected components of the
    bird's-eye-view cells the ``occupying`` (N,) bool points occupy (None: all); a point in a cell none of them
    occupies is in no component (-1)."""
    from scipy import ndimage

    from icpflow.scans.bev import occupied_cells
    from icpflow.scans.neighbours import GRID_MIN_CELLS

    if not len(points):
        return np.zeros(0, np.int64), 0
    occupying = np.ones(len(points), bool) if occupying is None else np.asarray(occupying, bool)
    cells = np.floor(points[:, :2] / points.dtype.type(cell)).astype(np.int64)
    if np.prod(cells.max(axis=0) - cells.min(axis=0) + 1, dtype=np.float64) > max(GRID_MIN_CELLS, 4 * len(points)):
        return sparse_components(cells, occupying)  # stray points far out: the box would not fit in memory
    cells, occupied = occupied_cells(points, points.dtype.type(cell), occupying)
    labels, count = ndimage.label(occupied, structure=np.ones((3, 3), bool))
    return labels[cells[:, 0], cells[:, 1]].astype(np.int64) - 1, int(count)


def sparse_components(cells: np.ndarray, occupying: np.ndarray) -> tuple[np.ndarray, int]:
    """:func:`components` from each point's (N, 2) int64 cell, in memory that follows the points: the occupied
    cells' 8-neighbour graph (scipy's connected components), numbered as ``ndimage.label`` numbers them (in the order
    of each component's first cell, x then y)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    occupied = np.unique(cells[occupying], axis=0)  # sorted by x, then y
    if not len(occupied):
        return np.full(len(cells), -1, np.int64), 0
    low = cells.min(axis=0)  # one key per cell of any point: the points' cells never alias an occupied one
    width = int(cells[:, 1].max() - low[1]) + 3

    def key(rows):
        return (rows[:, 0] - low[0] + 1) * width + (rows[:, 1] - low[1] + 1)

    keys = key(occupied)
    sources, targets = [np.arange(len(keys))], [np.arange(len(keys))]
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            if dx or dy:
                wanted = key(occupied + (dx, dy))
                at = np.minimum(np.searchsorted(keys, wanted), len(keys) - 1)
                hit = keys[at] == wanted
                sources.append(np.flatnonzero(hit))
                targets.append(at[hit])
    rows, columns = np.concatenate(sources), np.concatenate(targets)
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, columns)), shape=(len(keys), len(keys)))
    count, labels = connected_components(graph, directed=False)
    _, first = np.unique(labels, return_index=True)
    order = np.empty(count, np.int64)
    order[np.argsort(first)] = np.arange(count)  # components numbered by their first cell
    point_keys = key(cells)
    at = np.minimum(np.searchsorted(keys, point_keys), len(keys) - 1)
    inside = keys[at] == point_keys
    return np.where(inside, order[labels[at]], -1).astype(np.int64), int(count)


def median_at_least(values: np.ndarray, starts: np.ndarray, sizes: np.ndarray, threshold: float) -> np.ndarray:
    """(K,) bool: is ``numpy.median`` of each segment ``values[starts[k] : starts[k] + sizes[k]]`` (of the (N,) float
    ``values``; the segments tile them in order, none empty) at least ``threshold``? Exactly, without a sort: a
    segment of n values has its median there when more than n / 2 of them are; with exactly n / 2 (n even), when
    the mean of the two middle values, the largest below and the smallest at or above the threshold, is. (It
    replaced a Python loop of ``numpy.median`` per component, with ``np.take``'s gathers 0.4-0.8 ms of a pair.)"""
    above = values >= threshold
    count = np.add.reduceat(above.astype(np.int64), starts)
    below_largest = np.maximum.reduceat(np.where(above, -np.inf, values), starts)
    above_smallest = np.minimum.reduceat(np.where(above, values, np.inf), starts)
    halved = (2 * count == sizes) & ((below_largest + above_smallest) / 2.0 >= threshold)
    return (2 * count > sizes) | halved


@dataclass(frozen=True)
class _Components:
    """The pc0 points grouped by component (``order`` sorts them by component, ``bounds`` (count + 1,) the slices),
    sorted points and residuals (float64), and per component its box (``lows`` / ``highs``), mean residual
    ``means``, point count ``sizes``; ``above`` (N0,) the rows above the ground's surface, in sorted order."""

    order: np.ndarray
    bounds: np.ndarray
    points: np.ndarray
    residual: np.ndarray
    lows: np.ndarray
    highs: np.ndarray
    means: np.ndarray
    sizes: np.ndarray
    above: np.ndarray


@dataclass
class _Candidates:
    """The moving components with enough targets, one entry each: ``groups`` their pc0 rows (input order),
    ``movings`` the (thinned) points ICP moves and ``student_moved`` those moved by the student, ``fixeds`` the
    (thinned) pc1 targets above the ground, ``windows`` every pc1 point of the component's box, ``starts`` (K, 3) the
    mean predicted residual (ICP's initial translation)."""

    groups: list
    movings: list
    student_moved: list
    fixeds: list
    windows: list
    starts: np.ndarray


def refine_residual(
    pc0: np.ndarray,
    residual: np.ndarray,
    pc1: np.ndarray,
    cfg: RefineConfig,
    surface0: np.ndarray | None = None,
    surface1: np.ndarray | None = None,
):
    """((N0, 3) float32 refined residual flow, (N0,) bool: the points whose flow ICP replaced) of pc0 (N0, 3)
    (ego-compensated) with the student's residual (N0, 3) towards pc1 (N1, 3), all in the ego frame of t + dt.
    ``surface0`` (N0,) / ``surface1`` (N1,) bool: points of the ground's surface left in the scans (objects' feet,
    the ring the sensor draws around them: ``icpflow.scans.ground.GroundSegmenter.masks``); they belong to components
    and get an accepted motion where it fits them, but stay out of the ICP and its checks, whose matches they pull
    towards no motion. The stages are the module docstring's steps."""
    out, refined = np.array(residual, np.float32, copy=True), np.zeros(len(pc0), bool)
    if len(pc0) < cfg.min_points or len(pc1) < cfg.min_points:
        return out, refined
    above0 = np.ones(len(pc0), bool) if surface0 is None else ~np.asarray(surface0, bool)
    found = _components(pc0, residual, cfg, above0)
    if found is None:
        return out, refined
    parts, chosen = found
    candidates = _candidates(parts, chosen, pc1, cfg, surface1)
    if candidates is None:
        return out, refined
    transforms, accepted = _register(candidates, cfg)
    _apply(pc0, residual, candidates, transforms, accepted, cfg, out, refined)
    return out, refined


def _components(pc0, residual, cfg: RefineConfig, above0):
    """Steps 1 and 2: the components of pc0 and the moving ones among them (their indices), or None where there
    is none. Objects come from the points above the ground's surface; a surface point (an object's foot) joins the
    object in its cell, and one in no object's cell (the ground a moving object is joined to by) keeps the
    student's flow."""
    label, count = components(pc0, cfg.cell, above0)
    order = np.argsort(label.astype(np.int16) if count < 2**15 else label, kind="stable")  # 16 bits: a radix sort
    bounds = np.searchsorted(label[order], np.arange(count + 1))
    if count == 0:
        return None
    # per component at once (each has >= 1 point): box, mean residual; candidates by size, extent, speed
    # (np.take gathers rows 4x quicker than indexing)
    points = np.take(pc0, order, axis=0).astype(np.float64)
    moved = np.take(residual, order, axis=0).astype(np.float64)
    firsts = bounds[:-1]
    lows, highs = np.minimum.reduceat(points, firsts), np.maximum.reduceat(points, firsts)
    sizes = np.diff(bounds)
    means = np.add.reduceat(moved, firsts) / sizes[:, None]
    extents = np.linalg.norm((highs - lows)[:, :2], axis=1)
    fast = median_at_least(lengths(moved), firsts, sizes, cfg.min_motion)
    chosen = np.flatnonzero((sizes >= cfg.min_points) & (extents <= cfg.max_extent) & fast)
    if not len(chosen):
        return None
    return _Components(order, bounds, points, moved, lows, highs, means, sizes, above0[order]), chosen


def _candidates(parts: _Components, chosen, pc1, cfg: RefineConfig, surface1) -> _Candidates | None:
    """Step 3's input: each chosen component's points and its pc1 targets, the points of pc1 in its box moved by
    its mean residual and widened by ``margin``; None where no component has ``min_points`` of both."""
    from icpflow.scans.bev import in_box_cells

    lows, highs, means, bounds = parts.lows, parts.highs, parts.means, parts.bounds
    # pc1 sorted along x (each candidate's targets from one slice), of the points in the cells the candidates' boxes
    # cover only: the same targets in the same order as the whole scan sorted, at a fraction of the sort
    shifted = means[chosen] + np.array([[-cfg.margin], [cfg.margin]])[:, None]  # (2, K, 3): the boxes' two shifts
    by_x = in_box_cells(pc1, lows[chosen] + shifted[0], highs[chosen] + shifted[1], cfg.cell)
    by_x = by_x[np.argsort(pc1[by_x, 0], kind="stable")]
    pc1_x, pc1_sorted = pc1[by_x, 0], np.asarray(pc1[by_x], np.float64)
    registered1 = np.ones(len(pc1), bool) if surface1 is None else ~np.asarray(surface1, bool)[by_x]
    found = _Candidates([], [], [], [], [], np.zeros((0, 3)))
    kept = []
    for k in chosen:
        low, high = lows[k] + means[k] - cfg.margin, highs[k] + means[k] + cfg.margin
        first, last = np.searchsorted(pc1_x, low[0]), np.searchsorted(pc1_x, high[0], side="right")
        inside = np.all((pc1_sorted[first:last] >= low) & (pc1_sorted[first:last] <= high), axis=1)
        target = pc1_sorted[first:last][inside]
        fixed = target[registered1[first:last][inside]]
        rows = bounds[k] + np.flatnonzero(parts.above[bounds[k] : bounds[k + 1]])
        if len(fixed) < cfg.min_points or len(rows) < cfg.min_points:
            continue
        stride = -(-len(rows) // cfg.max_points)  # every stride-th point: at most max_points in pc0, and the
        rows = rows[::stride]  # targets thinned alike (the IoU ratio compares like densities)
        found.groups.append(parts.order[bounds[k] : bounds[k + 1]])
        found.movings.append(parts.points[rows])
        found.student_moved.append(parts.points[rows] + parts.residual[rows])
        found.fixeds.append(fixed[::stride])
        found.windows.append(target)
        kept.append(k)
    if not kept:
        return None
    found.starts = means[kept]
    return found


def _register(candidates: _Candidates, cfg: RefineConfig) -> tuple[np.ndarray, np.ndarray]:
    """Steps 3 and 4: each candidate's ICP motion (K, 4, 4) from its start and whether it is accepted (K,) bool."""
    from icpflow.teacher.checks import passes
    from icpflow.teacher.config import ChecksConfig, ICPConfig
    from icpflow.teacher.registration import register_stages_cpu

    starts, movings = candidates.starts, candidates.movings
    transforms = np.tile(np.eye(4), (len(movings), 1, 1))
    transforms[:, :3, 3] = starts
    # the teacher's rule (icp.static_tolerance): what no motion fits nearly as well stays static; only these
    # components need the match of no motion
    slow = (np.linalg.norm(starts, axis=1) <= cfg.static_max_motion) & (cfg.static_tolerance > 0)
    # every stage of the coarse-to-fine ICP and the quality (at the last truncation) of its motion, of no motion
    # (the slow ones) and of the student's own flow, in one compiled call
    transforms, errors, ious, still_errors, still_ious, student_errors, _ = register_stages_cpu(
        movings,
        candidates.fixeds,
        candidates.student_moved,
        transforms,
        cfg.max_corr,
        cfg.max_iter,
        ICPConfig().rel_rmse,
        True,
        slow,
    )
    static = slow & (still_errors <= errors * (1.0 + cfg.static_tolerance))
    transforms[static], errors[static], ious[static] = np.eye(4), still_errors[static], still_ious[static]
    centroids = np.stack([moving.mean(axis=0) for moving in movings])
    moved_centroids = np.einsum("kij,kj->ki", transforms[:, :3, :3], centroids) + transforms[:, :3, 3]
    change = np.linalg.norm(moved_centroids - centroids - starts, axis=1)
    checks = ChecksConfig(min_iou=cfg.min_iou, max_error=cfg.max_error)
    accepted = passes(transforms, errors, ious, np.inf, checks) & (errors < student_errors) & (change <= cfg.max_change)
    return transforms, accepted


def _apply(pc0, residual, candidates: _Candidates, transforms, accepted, cfg: RefineConfig, out, refined) -> None:
    """Step 5: each accepted motion written into ``out`` (and ``refined``) at the component's points it fits."""
    from icpflow.scans.neighbours import build_grid, nearest_distances
    from icpflow.teacher.registration import grid_cell

    cell = grid_cell(cfg.max_corr[-1])
    for k in np.flatnonzero(accepted):
        members, window = candidates.groups[k], candidates.windows[k]
        points = np.asarray(pc0[members], np.float64)
        flow = rigid_flow(points, transforms[k])
        grid = build_grid(window, cell)
        icp_gap = nearest_distances(points + flow, window, grid, cell, np.full(len(points), np.inf))
        # fits: icp_gap <= student_gap + point_slack; where the ICP's gap is within the slack, it fits whatever the
        # student's; elsewhere only a target nearer the student's flow than icp_gap - slack (a hair more: the
        # comparison below stays exact) can fail it, and a query bounded so stops early
        fits = icp_gap <= cfg.point_slack
        ask = np.flatnonzero(~fits)
        reach = (icp_gap[ask] - cfg.point_slack) * (1.0 + 1e-9)
        student_gap = nearest_distances(points[ask] + residual[members[ask]], window, grid, cell, reach)
        fits[ask] = icp_gap[ask] <= student_gap + cfg.point_slack
        out[members[fits]] = flow[fits]
        refined[members[fits]] = True
