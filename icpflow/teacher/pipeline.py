"""The ICP-Flow teacher: ``ICPFlow(cfg)(pc0, pc1, ego1_from_ego0=None, ground0=None, ground1=None)``.

Steps (one module each): ground removal and crop (``icpflow.scans.ground``), ego motion on the non-ground points
(``icpflow.scans.odometry``, when none is given), one clustering of the
fused non-ground points (``clustering``), candidate pairs in two stages (``pairing``), histogram or centroid
initialisation (``histogram``), ICP (``registration``), checks (``checks``), association (``association``),
optional recombination of split clusters (``merging``, with ``cfg.merging.distance`` > 0), optional rolling-shutter
refinement of moving matches (``deskew``, with ``cfg.deskew.enabled`` and per-point times
``time0``/``time1``), flow and confidence (``flow``). Frames: pc0 in the ego frame of t, pc1 in the ego frame of
t + dt; clustering and registration happen in pc1's frame after ego compensation of pc0.

Bad input: rows of pc0/pc1 with NaN or Inf are dropped before processing and counted (``dropped0``/``dropped1``);
their flow is reported as 0 with confidence 0 and ``valid0`` False. A non-rigid ``ego1_from_ego0``, wrong shapes
or wrong mask lengths raise ``ValueError`` with a one-line message; points are checked by
``icpflow.core.frame_pair.check_points`` ((N, >= 3), the first three columns used; a transposed array is an error).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from icpflow.core.frame_pair import check_points
from icpflow.core.geometry import rigid_problem, transform_points
from icpflow.scans.ground import GroundSegmenter
from icpflow.scans.odometry import estimate_ego_motion
from icpflow.teacher import association, checks, deskew, histogram, merging, registration
from icpflow.teacher.clustering import cluster_points
from icpflow.teacher.config import ICPConfig, ICPFlowConfig
from icpflow.teacher.flow import absorb, match_confidence, point_flow
from icpflow.teacher.pairing import cluster_stats, stage1_pairs, stage2_pairs
from icpflow.teacher.visibility import ScanView

STAGES = ("ego_motion", "ground", "clustering", "pairing", "histogram", "icp", "merging", "deskew", "flow")


@dataclass
class ICPFlowResult:
    """Teacher output for one pair. Per-point arrays follow the INPUT rows of pc0 (N0) / pc1 (N1).

    ``flow`` (N0, 3) float32 full flow; ``confidence`` (N0,) float32 in [0, 1]; ``labels0``/``labels1`` (N0,)/(N1,)
    int32 fused cluster ids (-1: noise, ground, cropped or dropped); ``pairs`` (M, 2) int32 matched (src, dst)
    cluster ids; ``transforms`` (M, 4, 4) float64 cluster motions in pc1's frame after ego compensation;
    ``errors``/``iou_ratios``/``match_confidence`` (M,); ``stage`` (M,) int8 (1 same label, 2 cross label, 3 merged
    by ``merging``);
    ``ego1_from_ego0`` (4, 4) used; ``ground0``/``ground1`` masks used; ``valid0``/``valid1`` finite rows;
    ``dropped0``/``dropped1`` counts of non-finite rows; ``n_candidates`` pairs registered; ``n_deskewed`` matches
    refined by the de-skew step; ``timings`` seconds per stage; ``candidates`` (only when the call asks for them,
    else None) every registered candidate pair of both stages, for diagnosis: ``src``/``dst`` (C,) cluster ids,
    ``stage`` (C,), ``init`` (C, 3) the histogram's (or centroid) start translation, ``transforms`` (C, 4, 4),
    ``errors``/``iou_ratios`` (C,), ``passed`` (C,) bool (the checks), ``chosen`` (C,) bool (the association).
    """

    flow: np.ndarray
    confidence: np.ndarray
    labels0: np.ndarray
    labels1: np.ndarray
    pairs: np.ndarray
    transforms: np.ndarray
    errors: np.ndarray
    iou_ratios: np.ndarray
    match_confidence: np.ndarray
    stage: np.ndarray
    ego1_from_ego0: np.ndarray
    ground0: np.ndarray
    ground1: np.ndarray
    valid0: np.ndarray
    valid1: np.ndarray
    dropped0: int
    dropped1: int
    n_candidates: int
    n_deskewed: int = 0
    timings: dict = field(default_factory=dict)
    candidates: dict | None = None


def _as_times(name: str, value, count: int) -> np.ndarray | None:
    if value is None:
        return None
    array = np.asarray(value)
    if array.shape != (count,):
        raise ValueError(f"ICPFlow: {name} must have shape ({count},), got {array.shape}")
    if not np.issubdtype(array.dtype, np.floating) or not np.isfinite(array).all():
        raise ValueError(f"ICPFlow: {name} must hold finite float seconds")
    return array.astype(np.float64)


def _as_mask(name: str, value, count: int) -> np.ndarray | None:
    if value is None:
        return None
    array = np.asarray(value)
    if array.shape != (count,):
        raise ValueError(f"ICPFlow: {name} must have shape ({count},), got {array.shape}")
    if array.dtype != np.bool_:
        raise ValueError(f"ICPFlow: {name} must be bool, got {array.dtype}")
    return array


def _prefer_static(result, clouds, params: ICPConfig, seed: int = 0, view: ScanView | None = None) -> None:
    """Pairs whose error at the identity is at most ``(1 + params.static_tolerance)`` times their registered error
    keep the identity (no motion), with its error and IoU ratio (``result`` is updated in place). Scans sample a
    static surface differently (scan lines move with the ego), so a small slide along walls often fits slightly
    better than no motion at all; a real motion fits far better than the identity. The errors compared are the
    mean errors (the smaller of the two directions). The identity's quality is the one
    ``result`` holds (``register_clusters(identity=True)``), else measured here by a registration with no
    iteration.

    With ``params.plane_gain`` > 0 a pair that moves must also fit its destination's local planes better than the
    identity does (``registration.plane_errors``): by ``(1 + plane_gain)`` times plus ``plane_margin`` where its
    centroid moves at most ``plane_reach`` m, by ``plane_margin`` where it moves further. A real scan draws a static
    wall or trunk with other scan lines in the next frame, and point-to-point ICP slides it along its own surface to
    lay the lines onto each other; a plane's distance does not reward that slide, and a real motion gains on it
    many times over. A long vehicle sliding along itself gains less (only its ends), hence the weaker test for
    long motions. With ``view`` (pc1's ``ScanView``) the test leaves out the src points pc1 could not see where the
    identity puts them: a static object leaving a one-sided view is half drawn in pc1, and its unseen half would
    reward sliding the whole onto the drawn part."""
    identity = np.tile(np.eye(4), (len(clouds), 1, 1))
    if result.identity_error is None:
        still = registration.register_clusters(clouds, identity, dataclasses.replace(params, max_iter=0), seed)
        result.identity_error, result.identity_iou = still.mean_error, still.iou_ratio
        result.identity_symmetric_error = still.symmetric_error
    static = result.identity_error <= result.mean_error * (1.0 + params.static_tolerance)
    if params.plane_gain > 0:
        centroids = np.array([a.mean(axis=0) if len(a) else np.zeros(3) for a, _ in clouds]).reshape(-1, 3)
        shift = np.einsum("pij,pj->pi", result.transforms[:, :3, :3], centroids) + result.transforms[:, :3, 3]
        short = np.linalg.norm(shift - centroids, axis=1) <= params.plane_reach
        test = np.flatnonzero(~static)
        tested = [_in_view(clouds[p], view) for p in test]
        still, moved = registration.plane_errors(tested, result.transforms[test], params.max_points, seed)
        gain = np.where(short[test], params.plane_gain, 0.0)
        static[test[still <= moved * (1.0 + gain) + params.plane_margin]] = True
    result.transforms[static] = identity[static]
    result.mean_error[static] = result.identity_error[static]
    result.iou_ratio[static] = result.identity_iou[static]
    result.symmetric_error[static] = result.identity_symmetric_error[static]


def _in_view(cloud: tuple[np.ndarray, np.ndarray], view: ScanView | None) -> tuple[np.ndarray, np.ndarray]:
    """A (src, dst) pair with the src points outside ``view`` dropped (all kept without a view, with a full one, or
    where fewer than 3 would be left)."""
    src, dst = cloud
    if view is None or view.full or len(src) == 0:
        return cloud
    seen = view.sees(src)
    return (src[seen], dst) if seen.sum() >= 3 else cloud


def _twin_shares(dst, dst_stats, clouds, dst_ids, transforms, ask, radius: float = 0.2) -> np.ndarray:
    """(P,) for P candidates (src points ``clouds[p][0]``, dst cluster ``dst_ids[p]``, ``transforms`` (P, 4, 4))
    where ``ask`` (P,) bool, with ``dst`` (M, 3) pc1's non-ground points and their ``ClusterStats``: the share of
    the src points that, where they stand (pc1's frame, ego-compensated), have a point of a pc1 cluster other than
    the candidate's dst within ``radius`` m; 0 elsewhere and for a pair that keeps the identity. A real mover leaves
    its place empty or to its own next points; a static object matched to a neighbour (a row of poles, a parked car
    beside another) finds its own next points, labelled otherwise, still where it stands. Only the clusters whose
    boxes reach the src's are searched."""
    from scipy.spatial import cKDTree

    shares = np.zeros(len(dst_ids))
    moves = np.abs(transforms - np.eye(4)).reshape(len(transforms), -1).max(axis=1, initial=0.0) > 0
    present = np.flatnonzero(dst_stats.count > 0)
    for p in np.flatnonzero(moves & ask):
        points = clouds[p][0]
        if not len(points):
            continue
        low, high = points.min(axis=0) - radius, points.max(axis=0) + radius
        reach = (dst_stats.lower[present] <= high).all(axis=1) & (dst_stats.upper[present] >= low).all(axis=1)
        others = [label for label in present[reach] if label != dst_ids[p]]
        if not others:
            continue
        distance, _ = cKDTree(np.concatenate([dst_stats.points(dst, label) for label in others])).query(
            points, distance_upper_bound=radius
        )
        shares[p] = float(np.isfinite(distance).mean())
    return shares


class StageClock:
    """Seconds per teacher stage of one call: ``with clock("icp"): ...`` adds the block's wall time to
    ``clock.seconds["icp"]`` (every stage of :data:`STAGES` starts at 0; a stage may run several times)."""

    def __init__(self):
        self.seconds = dict.fromkeys(STAGES, 0.0)

    @contextmanager
    def __call__(self, stage: str):
        tic = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] += time.perf_counter() - tic


@dataclass(frozen=True)
class _Inputs:
    """One call's checked input: ``pc0`` / ``pc1`` the input rows (N0, 3) / (N1, 3), ``valid0`` / ``valid1`` the
    finite ones, ``pc0_ok`` / ``pc1_ok`` those rows; the optional (N,) ground masks and per-point times of the
    input rows, ``gap``, ``dt`` and whether the de-skew runs."""

    pc0: np.ndarray
    pc1: np.ndarray
    valid0: np.ndarray
    valid1: np.ndarray
    ground0: np.ndarray | None
    ground1: np.ndarray | None
    time0: np.ndarray | None
    time1: np.ndarray | None
    gap: int
    dt: float | None
    deskew: bool

    @property
    def pc0_ok(self) -> np.ndarray:
        return self.pc0[self.valid0]

    @property
    def pc1_ok(self) -> np.ndarray:
        return self.pc1[self.valid1]


@dataclass(frozen=True)
class _Scans:
    """The finite rows of both scans split for the teacher: ``ground*`` the ground masks, ``surface*`` the ground
    left out of the odometry, ``keep*`` the non-ground rows inside the crop."""

    pc0: np.ndarray
    pc1: np.ndarray
    ground0: np.ndarray
    ground1: np.ndarray
    surface0: np.ndarray
    surface1: np.ndarray
    keep0: np.ndarray
    keep1: np.ndarray


class ICPFlow:
    """Learning-free scene flow between two LiDAR scans (see the module docstring)."""

    def __init__(self, cfg: ICPFlowConfig | None = None):
        self.cfg = cfg if cfg is not None else ICPFlowConfig.preset("av2")
        if not isinstance(self.cfg, ICPFlowConfig):
            raise ValueError(f"ICPFlow: cfg must be an ICPFlowConfig, got {type(self.cfg).__name__}")
        self.ground = GroundSegmenter(self.cfg)

    def __call__(
        self,
        pc0,
        pc1,
        ego1_from_ego0=None,
        ground0=None,
        ground1=None,
        time0=None,
        time1=None,
        *,
        gap: int = 1,
        dt: float | None = None,
        candidates: bool = False,
    ) -> ICPFlowResult:
        """Flow of pc0 (N0, 3) towards pc1 (N1, 3); ``gap`` k: frames between the scans (window scales with k).

        ``time0`` (N0,) / ``time1`` (N1,): optional capture time of each point in seconds after its scan's
        timestamp, and ``dt`` the seconds between the two timestamps; with ``cfg.deskew.enabled`` they drive the
        rolling-shutter refinement (``deskew``), which then needs all three. Without them nothing is de-skewed.
        ``candidates``: also return every registered candidate pair (``ICPFlowResult.candidates``).
        """
        inputs = self._checked(pc0, pc1, ground0, ground1, time0, time1, gap, dt)
        clock = StageClock()
        with clock("ground"):
            scans = self._split(inputs)
        with clock("ego_motion"):
            ego = self._ego_motion(scans, ego1_from_ego0)
        with clock("clustering"):
            src, dst = transform_points(ego, scans.pc0[scans.keep0]), scans.pc1[scans.keep1]
            fused = cluster_points(np.concatenate([src, dst]), self.cfg.clustering)
            src_labels, dst_labels = fused[: len(src)], fused[len(src) :]
        window = self._window(ego, int(inputs.gap))
        view = ScanView.of(scans.pc1)
        matches, tried, src_stats, dst_stats = self._match(src, dst, src_labels, dst_labels, window, clock, view)
        if self.cfg.merging.distance > 0:
            with clock("merging"):
                src_stats, dst_stats = self._merge(
                    src, dst, src_labels, dst_labels, src_stats, dst_stats, matches, window, view
                )
        with clock("deskew"):
            n_deskewed = self._deskew(inputs, scans, src, dst, src_stats, dst_stats, matches, window)
        with clock("flow"):
            arrays = self._flow(inputs, scans, ego, src_labels, dst_labels, matches)
        return ICPFlowResult(
            **arrays,
            ego1_from_ego0=ego,
            valid0=inputs.valid0,
            valid1=inputs.valid1,
            dropped0=int((~inputs.valid0).sum()),
            dropped1=int((~inputs.valid1).sum()),
            n_deskewed=n_deskewed,
            timings=clock.seconds,
            candidates=tried if candidates else None,
            **matches,
        )

    def _checked(self, pc0, pc1, ground0, ground1, time0, time1, gap, dt) -> _Inputs:
        """The call's arguments checked (one-line ``ValueError`` otherwise) and the finite rows found; non-finite
        rows are not an error: they are dropped and counted."""
        pc0 = check_points(pc0, "ICPFlow", "pc0", finite=False)
        pc1 = check_points(pc1, "ICPFlow", "pc1", finite=False)
        ground0, ground1 = _as_mask("ground0", ground0, len(pc0)), _as_mask("ground1", ground1, len(pc1))
        time0, time1 = _as_times("time0", time0, len(pc0)), _as_times("time1", time1, len(pc1))
        max_gap = self.cfg.pairing.max_frame_gap
        if isinstance(gap, bool) or not isinstance(gap, (int, np.integer)) or not 1 <= gap <= max_gap:
            raise ValueError(f"ICPFlow: gap must be an integer in [1, {max_gap}], got {gap!r}")
        deskew_on = self.cfg.deskew.enabled and (time0 is not None or time1 is not None)
        if deskew_on and (time0 is None or time1 is None or dt is None):
            raise ValueError("ICPFlow: de-skew needs time0, time1 and dt together (or cfg.deskew.enabled=False)")
        if deskew_on and not (isinstance(dt, (int, float, np.integer, np.floating)) and np.isfinite(dt) and dt > 0):
            raise ValueError(f"ICPFlow: dt must be a positive number of seconds, got {dt!r}")
        valid0, valid1 = np.isfinite(pc0).all(axis=1), np.isfinite(pc1).all(axis=1)
        return _Inputs(pc0, pc1, valid0, valid1, ground0, ground1, time0, time1, gap, dt, deskew_on)

    def _split(self, inputs: _Inputs) -> _Scans:
        """Step 1: the ground of each scan (given, or segmented here) and the non-ground rows inside the crop."""
        crop = self.cfg.crop_xy
        parts = []
        for points, given, valid in (
            (inputs.pc0_ok, inputs.ground0, inputs.valid0),
            (inputs.pc1_ok, inputs.ground1, inputs.valid1),
        ):
            ground, surface = self.ground.masks(points) if given is None else (given[valid], given[valid])
            parts.append((points, ground, surface, ~ground & (np.abs(points[:, :2]) < crop).all(axis=1)))
        (pc0, g0, s0, keep0), (pc1, g1, s1, keep1) = parts
        return _Scans(pc0, pc1, g0, g1, s0, s1, keep0, keep1)

    def _ego_motion(self, scans: _Scans, given) -> np.ndarray:
        """Step 2: ``given`` (4, 4) checked, or the ego motion estimated on the scans without the ground's surface
        (also when ``ego_motion.method`` is ``kiss_icp``)."""
        if given is not None and self.cfg.ego_motion.method != "kiss_icp":
            ego = np.asarray(given, dtype=np.float64)
            problem = rigid_problem(ego)
            if problem:
                raise ValueError(f"ICPFlow: ego1_from_ego0 {problem}")
            return ego
        try:
            ego = estimate_ego_motion(scans.pc0, scans.pc1, self.cfg, scans.surface0, scans.surface1)
        except (RuntimeError, ValueError, MemoryError) as error:
            raise ValueError(f"ICPFlow: ego-motion estimation failed ({type(error).__name__}: {error})") from None
        if ego is None:
            raise ValueError("ICPFlow: no ego motion fits the two scans (do they overlap?); pass ego1_from_ego0")
        if rigid_problem(ego):
            raise ValueError(f"ICPFlow: the estimated ego motion {rigid_problem(ego)}")
        return ego

    def _merge(self, src, dst, src_labels, dst_labels, src_stats, dst_stats, matches, window, view) -> tuple:
        """Step 8b: recombine the clusters of one rigid object that the fused clustering split (``merging``;
        ``matches`` updated in place); the two scans' ``ClusterStats`` after it."""
        cfg = self.cfg
        _, src_stats, dst_stats = merging.merge_split_clusters(
            src,
            dst,
            src_labels,
            dst_labels,
            src_stats,
            dst_stats,
            matches,
            lambda clouds, centroids, max_points: self._register_clouds(
                clouds, centroids, window, StageClock(), max_points, view
            ),
            cfg.merging,
            cfg.icp,
            cfg.clustering.min_cluster_size,
            cfg.seed,
        )
        return src_stats, dst_stats

    def _deskew(self, inputs: _Inputs, scans: _Scans, src, dst, src_stats, dst_stats, matches, window) -> int:
        """Step 8c: the rolling-shutter refinement of the moving matches where the call gave times; how many."""
        if not inputs.deskew:
            return 0
        time0 = inputs.time0[inputs.valid0][scans.keep0]
        time1 = inputs.time1[inputs.valid1][scans.keep1]
        return deskew.refine(src, dst, src_stats, dst_stats, time0, time1, matches, float(inputs.dt), window, self.cfg)

    def _flow(self, inputs: _Inputs, scans: _Scans, ego, src_labels, dst_labels, matches) -> dict:
        """Step 9: flow and confidence per point (absorbing unclustered points near a match's cluster), the labels
        and ground masks, all put back on the input rows (0 / -1 / False on the non-finite ones)."""
        cfg, pc0, valid0, valid1 = self.cfg, scans.pc0, inputs.valid0, inputs.valid1
        labels_ok0 = np.full(len(pc0), -1, dtype=np.int32)
        labels_ok0[scans.keep0] = src_labels
        flow_labels = labels_ok0
        if cfg.flow.absorb_radius > 0:
            inside = (np.abs(pc0[:, :2]) < cfg.crop_xy).all(axis=1)
            flow_labels = absorb(pc0, labels_ok0, ego, matches["pairs"][:, 0], cfg.flow.absorb_radius, inside)
        flow_ok, conf_ok = point_flow(
            pc0, flow_labels, ego, matches["pairs"][:, 0], matches["transforms"], matches["match_confidence"]
        )
        count0, count1 = len(inputs.pc0), len(inputs.pc1)
        flow, confidence = np.zeros((count0, 3), dtype=np.float32), np.zeros(count0, dtype=np.float32)
        flow[valid0], confidence[valid0] = flow_ok, conf_ok
        labels0, labels1 = np.full(count0, -1, dtype=np.int32), np.full(count1, -1, dtype=np.int32)
        labels0[valid0] = labels_ok0
        labels1[np.flatnonzero(valid1)[scans.keep1]] = dst_labels
        ground0, ground1 = np.zeros(count0, dtype=bool), np.zeros(count1, dtype=bool)
        ground0[valid0], ground1[valid1] = scans.ground0, scans.ground1
        return {
            "flow": flow,
            "confidence": confidence,
            "labels0": labels0,
            "labels1": labels1,
            "ground0": ground0,
            "ground1": ground1,
        }

    def _window(self, ego: np.ndarray, gap: int) -> float:
        """The pair's search window (m, ``PairingConfig.window``), held at the widest one the vote holds
        (``HistogramConfig.largest_window``) with one warning: an ego motion of tens of metres between the scans (a
        wrong pose, a long gap) would otherwise ask for a vote of gigabytes per cluster pair."""
        window = self.cfg.pairing.window(float(np.linalg.norm(ego[:3, 3])), gap)
        largest = self.cfg.histogram.largest_window()
        if window > largest:
            warnings.warn(
                f"ICPFlow: an ego motion of {np.linalg.norm(ego[:3, 3]):.1f} m between the scans widens the search "
                f"window to {window:.1f} m; held at {largest:.1f} m, the widest the vote holds at histogram.bin_size "
                f"{self.cfg.histogram.bin_size:g} m",
                RuntimeWarning,
                stacklevel=3,
            )
            return largest
        return window

    def _match(self, src, dst, src_labels, dst_labels, window, clock: StageClock, view=None) -> tuple:
        """Steps 4 to 8 over both stages: the chosen matches as arrays, every candidate tried (see
        ``ICPFlowResult``) and the two scans' ``ClusterStats``."""
        cfg = self.cfg
        with clock("pairing"):
            n_labels = int(max(src_labels.max(initial=-1), dst_labels.max(initial=-1))) + 1
            src_stats = cluster_stats(src, src_labels, n_labels)
            dst_stats = cluster_stats(dst, dst_labels, n_labels)
            s1, d1 = stage1_pairs(src_stats, dst_stats, window, cfg.pairing, cfg.clustering.min_cluster_size)
        first = self._register(src, dst, src_stats, dst_stats, s1, d1, window, clock, view)

        with clock("pairing"):
            src_free = np.ones(n_labels, dtype=bool)
            dst_free = np.ones(n_labels, dtype=bool)
            src_free[first["pairs"][:, 0]] = False
            dst_free[first["pairs"][:, 1]] = False
            s2, d2 = stage2_pairs(
                src_stats, dst_stats, src_free, dst_free, window, cfg.pairing, cfg.clustering.min_cluster_size
            )
        second = self._register(src, dst, src_stats, dst_stats, s2, d2, window, clock, view)

        out = {key: np.concatenate([first[key], second[key]]) for key in first if key not in ("n_candidates", "tried")}
        out["stage"] = np.concatenate(
            [np.full(len(first["errors"]), 1, np.int8), np.full(len(second["errors"]), 2, np.int8)]
        )
        out["n_candidates"] = first["n_candidates"] + second["n_candidates"]
        tried = {key: np.concatenate([first["tried"][key], second["tried"][key]]) for key in first["tried"]}
        tried["stage"] = np.repeat(np.array([1, 2], np.int8), [first["n_candidates"], second["n_candidates"]])
        return out, tried, src_stats, dst_stats

    def _register(self, src, dst, src_stats, dst_stats, src_ids, dst_ids, window, clock, view) -> dict:
        """Initialise, register, check and associate candidate pairs; the chosen ones as arrays."""
        cfg = self.cfg
        n = len(src_ids)
        clouds = [(src_stats.points(src, s), dst_stats.points(dst, d)) for s, d in zip(src_ids, dst_ids)]
        tried = self._register_clouds(clouds, src_stats.centroid[src_ids], window, clock, view=view)
        if cfg.checks.max_twin_share < 1 and n:
            shares = _twin_shares(dst, dst_stats, clouds, dst_ids, tried["transforms"], tried["passed"])
            tried["passed"] &= shares <= cfg.checks.max_twin_share
        with clock("icp"):
            chosen = association.associate(
                src_ids, dst_ids, tried["errors"], tried["passed"], method=cfg.association.method
            )
        pick = np.flatnonzero(chosen)
        return {
            "pairs": np.stack([src_ids[pick], dst_ids[pick]], axis=1).astype(np.int32).reshape(-1, 2),
            "transforms": tried["transforms"][pick],
            "errors": tried["errors"][pick],
            "iou_ratios": tried["iou_ratios"][pick],
            "match_confidence": tried["match_confidence"][pick],
            "n_candidates": n,
            "tried": {
                "src": np.asarray(src_ids, np.int64),
                "dst": np.asarray(dst_ids, np.int64),
                "chosen": chosen,
                **{key: tried[key] for key in ("init", "transforms", "errors", "iou_ratios", "passed")},
            },
        }

    def _register_clouds(
        self, clouds, src_centroids, window, clock, max_points: int | None = None, view: ScanView | None = None
    ) -> dict:
        """Steps 5 to 7 for P candidate pairs ``clouds`` ((src (Ns, 3), dst (Nd, 3)), pc1's frame) with their
        source centroids (P, 3), ICP on at most ``max_points`` per cluster if given (else ``icp.max_points``),
        ``view`` pc1's ``ScanView`` for the static test (``_prefer_static``):
        ``init`` (P, 3) start translations, ``transforms`` (P, 4, 4), ``errors``,
        ``symmetric_errors`` (``registration.RegistrationResult``), ``iou_ratios``, ``match_confidence`` (P,),
        ``passed`` (P,) bool."""
        cfg = self.cfg
        n = len(clouds)
        if n == 0:
            return {
                "init": np.zeros((0, 3)),
                "transforms": np.zeros((0, 4, 4)),
                "errors": np.zeros(0),
                "symmetric_errors": np.zeros(0),
                "iou_ratios": np.zeros(0),
                "match_confidence": np.zeros(0, np.float32),
                "passed": np.zeros(0, bool),
            }
        with clock("histogram"):
            if cfg.histogram.init == "histogram":
                translations, _ = histogram.initial_translations(clouds, np.full(n, window), cfg.histogram, cfg.seed)
            else:
                translations = np.array([histogram.centroid_translation(a, b) for a, b in clouds]).reshape(n, 3)
            inits = np.tile(np.eye(4), (n, 1, 1))
            inits[:, :3, 3] = translations
        with clock("icp"):
            icp = cfg.icp
            if max_points is not None:
                icp = dataclasses.replace(cfg.icp, max_points=min(cfg.icp.max_points, max_points))
            result = registration.register_clusters(clouds, inits, icp, cfg.seed, identity=icp.static_tolerance > 0)
            if icp.static_tolerance > 0:
                _prefer_static(result, clouds, icp, cfg.seed, view)
            windows = np.full(n, window)
            ok = checks.passes(
                result.transforms, result.mean_error, result.iou_ratio, windows, cfg.checks, src_centroids=src_centroids
            )
        errors = result.mean_error.astype(np.float64)
        ious = result.iou_ratio.astype(np.float64)
        return {
            "init": translations,
            "transforms": result.transforms,
            "errors": errors,
            "symmetric_errors": result.symmetric_error.astype(np.float64),
            "iou_ratios": ious,
            "match_confidence": match_confidence(errors, ious, cfg.flow, cfg.checks.max_error),
            "passed": ok,
        }
