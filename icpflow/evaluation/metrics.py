"""Scene-flow metrics: ICP-Flow paper splits (EPE, Acc-S, Acc-R, Outliers) and Argoverse 2 Threeway / bucketed EPE.

All inputs are in pc0's ego frame: pc0 (N, 3) metres, predicted and ground-truth FULL flow (N, 3) metres per pair,
ego1_from_ego0 (4, 4). EPE on full flow equals EPE on residual (ego-compensated) flow, since both flows differ from
their residual by the same ego flow. Speeds and dynamic masks use the ground-truth residual flow.

Relative error = EPE / max(||gt residual flow||, eps) (eps = 1e-6 m): on static points the relative criterion is
then almost never met for Acc and almost always met for Outliers unless EPE == 0; pass ``relative_to="full"`` to
divide by the full-flow norm instead (the PCAccumulation / FlowStep3D convention).
"""

from __future__ import annotations

import warnings

import numpy as np

from icpflow.core.classes import AV2_CATEGORIES, AV2_META, META_CLASSES  # noqa: F401 (the metrics' names too)
from icpflow.core.geometry import ego_flow

CATEGORIES = ("dynamic_fg", "static_fg", "static_bg", "overall")
COLUMNS = ("EPE", "AccS", "AccR", "Outliers")
RELATIVE_EPS = 1e-6


def _meta_index(classes: np.ndarray, class_to_meta: dict[int, str], metas: tuple[str, ...]) -> np.ndarray:
    """(N,) int index into ``metas``; -1 for classes mapped to no meta-class."""
    table = np.full(max(max(class_to_meta), int(classes.max(initial=0))) + 1, -1, np.int64)
    for cls, meta in class_to_meta.items():
        if meta in metas:
            table[cls] = metas.index(meta)
    return table[classes]


def _check(pc0, pred_flow, gt_flow, classes) -> None:
    n = len(pc0)
    for name, arr in (("pred_flow", pred_flow), ("gt_flow", gt_flow)):
        if arr is not None and np.shape(arr) != (n, 3):
            raise ValueError(f"metrics: {name} has shape {np.shape(arr)}, expected ({n}, 3) like pc0")
    if np.shape(classes) != (n,):
        raise ValueError(f"metrics: classes has shape {np.shape(classes)}, expected ({n},)")
    if n and np.min(classes) < 0:
        raise ValueError(f"metrics: classes has negative values ({np.min(classes)}); 0 means background")


class PairTruth:
    """The ground-truth side of one pair's metrics, computed once and shared by every method scored on the pair.

    ``pc0`` (N, 3) metres and FULL ``gt_flow`` (N, 3) in pc0's ego frame, ``ego1_from_ego0`` (4, 4), ``classes``
    (N,) (0 = background); ``scored`` (N,) bool: ``flow_valid`` and, unless ``include_ground``, not ``ground``.
    :meth:`epe` gives a prediction's per-point EPE; :meth:`paper` and :meth:`buckets` select the points of the
    paper's splits and of the AV2 buckets once, and turn any EPE into their sums.
    """

    def __init__(self, pc0, gt_flow, ego1_from_ego0, classes, ground=None, flow_valid=None, include_ground=False):
        _check(pc0, None, gt_flow, classes)
        self.pc0 = np.asarray(pc0, np.float64)
        self.gt_flow = np.asarray(gt_flow, np.float64)
        self.residual = self.gt_flow - ego_flow(np.asarray(pc0), ego1_from_ego0)
        self.speed = np.linalg.norm(self.residual, axis=1)  # ||gt residual flow||, metres per pair
        self.classes = np.asarray(classes, np.int64)
        self.scored = np.ones(len(self.pc0), bool)
        if ground is not None and not include_ground:
            self.scored &= ~np.asarray(ground, bool)
        if flow_valid is not None:
            self.scored &= np.asarray(flow_valid, bool)

    @classmethod
    def of_pair(cls, pair, include_ground: bool = False) -> PairTruth:
        """The truth of a FramePair holding ground truth (flow, classes, ego1_from_ego0); ValueError otherwise."""
        if not pair.has_ground_truth or pair.classes is None:
            raise ValueError(f"{pair.source}: metrics need ground-truth flow and classes")
        if pair.ego1_from_ego0 is None:  # the splits are by motion beyond the ego's: no estimate stands in for it
            raise ValueError(
                f"{pair.source}: has ground-truth flow but no ego motion (ego1_from_ego0, or pose0 and pose1): the "
                "metrics split points into static and dynamic by their motion beyond the ego's; add it to score"
            )
        return cls(
            pair.pc0, pair.flow, pair.ego1_from_ego0, pair.classes, pair.ground0, pair.flow_valid, include_ground
        )

    def epe(self, pred_flow) -> np.ndarray:
        """(N,) float64 end-point error (m) of a FULL flow prediction (N, 3)."""
        _check(self.pc0, pred_flow, None, self.classes)
        return np.linalg.norm(np.asarray(pred_flow, np.float64) - self.gt_flow, axis=1)

    def in_box(self, half_width: float | None, strict: bool = False) -> np.ndarray:
        """(N,) bool: scored points with |x|, |y| <= half_width (< when ``strict``; None: every scored point)."""
        if half_width is None:
            return self.scored.copy()
        xy = np.abs(self.pc0[:, :2])
        return self.scored & np.all(xy < half_width if strict else xy <= half_width, axis=1)

    def paper(self, dt=0.1, crop=32.0, dynamic_speed=0.5, relative_to="residual") -> PaperSplits:
        """The ICP-Flow paper's splits of this pair (see :func:`pair_stats`)."""
        if relative_to not in ("residual", "full"):
            raise ValueError(f"metrics: relative_to must be 'residual' or 'full', got {relative_to!r}")
        norm = self.speed if relative_to == "residual" else np.linalg.norm(self.gt_flow, axis=1)
        keep = self.in_box(crop)
        dynamic = self.speed / dt > dynamic_speed
        fg = self.classes > 0
        masks = {"dynamic_fg": dynamic & fg, "static_fg": ~dynamic & fg, "static_bg": ~dynamic & ~fg, "overall": True}
        return PaperSplits({name: keep & mask for name, mask in masks.items()}, np.maximum(norm, RELATIVE_EPS))

    def buckets(self, class_to_meta=None, edges=None, metas=META_CLASSES, distance=35.0) -> Buckets:
        """The AV2 buckets of this pair (see :func:`av2_bucket_stats`)."""
        class_to_meta = AV2_META if class_to_meta is None else class_to_meta
        edges = BUCKET_EDGES if edges is None else edges
        meta = _meta_index(self.classes, class_to_meta, metas)
        keep = self.in_box(distance, strict=True) & (meta >= 0)
        bucket = np.searchsorted(edges, self.speed[keep], side="right") - 1
        return Buckets(keep, meta[keep] * (len(edges) - 1) + bucket, self.speed[keep], (len(metas), len(edges) - 1))


class PaperSplits:
    """One pair's points per split (``masks``: category -> (N,) bool) and the relative-error base (N,) (m)."""

    def __init__(self, masks: dict[str, np.ndarray], relative_base: np.ndarray):
        self.masks, self.relative_base = masks, relative_base

    def sums(self, epe: np.ndarray) -> dict[str, np.ndarray]:
        """{category: [epe_sum, accs_count, accr_count, outlier_count, n]} (float64 (5,)) of per-point EPE (N,)."""
        rel = epe / self.relative_base
        hits = np.stack(
            [epe, (epe < 0.05) | (rel < 0.05), (epe < 0.1) | (rel < 0.1), (epe > 0.3) | (rel > 0.1), np.ones_like(epe)],
            axis=1,
        )
        return {name: hits[mask].sum(axis=0) for name, mask in self.masks.items()}


class Buckets:
    """One pair's points in AV2 (meta-class, speed bucket) cells: ``keep`` (N,) bool, each kept point's flat cell
    index and speed (m per frame), the cells' ``shape`` (metas, buckets)."""

    def __init__(self, keep: np.ndarray, cell: np.ndarray, speed: np.ndarray, shape: tuple[int, int]):
        self.keep, self.cell, self.speed, self.shape = keep, cell, speed, shape

    def sums(self, epe: np.ndarray) -> np.ndarray:
        """(metas, buckets, 3) float64 [epe_sum, speed_sum, count] of per-point EPE (N,)."""
        size = self.shape[0] * self.shape[1]
        columns = [np.bincount(self.cell, weights=w, minlength=size) for w in (epe[self.keep], self.speed)]
        columns.append(np.bincount(self.cell, minlength=size).astype(np.float64))
        return np.stack(columns, axis=-1).reshape(*self.shape, 3)


def pair_stats(
    pc0,
    pred_flow,
    gt_flow,
    ego1_from_ego0,
    classes,
    ground=None,
    flow_valid=None,
    dt: float = 0.1,
    crop: float | None = 32.0,
    include_ground: bool = False,
    dynamic_speed: float = 0.5,
    relative_to: str = "residual",
) -> dict[str, np.ndarray]:
    """Sums for one pair: {category: [epe_sum, accs_count, accr_count, outlier_count, n]} (float64 (5,)).

    Points kept: |x|, |y| <= crop in pc0's ego frame (None = no crop), not ground unless ``include_ground``, and
    ``flow_valid``. Dynamic = ||gt residual|| / dt > dynamic_speed; foreground = classes > 0. ``overall`` holds all
    kept points (including dynamic background points, which are in none of the three splits). Scoring several
    predictions of one pair: :class:`PairTruth` (the selection is then made once).
    """
    truth = PairTruth(pc0, gt_flow, ego1_from_ego0, classes, ground, flow_valid, include_ground)
    splits = truth.paper(dt, crop, dynamic_speed, relative_to)
    return splits.sums(truth.epe(pred_flow))


def frame_pair_stats(
    pair, pred_flow, crop=32.0, include_ground=False, dynamic_speed=0.5, relative_to="residual"
) -> dict[str, np.ndarray]:
    """:func:`pair_stats` for a FramePair holding ground truth (flow, classes, ego1_from_ego0)."""
    truth = PairTruth.of_pair(pair, include_ground)
    return truth.paper(pair.dt, crop, dynamic_speed, relative_to).sums(truth.epe(pred_flow))


def _means(sums: np.ndarray) -> dict[str, float]:
    n = sums[4]
    with np.errstate(invalid="ignore", divide="ignore"):
        values = sums[:4] / n if n > 0 else np.full(4, np.nan)
    return dict(zip(COLUMNS, map(float, values))) | {"count": int(n)}


class MetricAccumulator:
    """Takes pairs one by one; keeps only sums. ``table()`` -> {"point_weighted"|"per_pair": {category: row}}.

    Point-weighted: sums over all points of all pairs (the paper). Per-pair: mean over pairs of each pair's metric,
    skipping pairs where the category is empty; its ``count`` is the number of pairs that contributed.
    """

    def __init__(self) -> None:
        self.sums = {c: np.zeros(5) for c in CATEGORIES}
        self.pair_sums = {c: np.zeros(4) for c in CATEGORIES}
        self.pair_counts = dict.fromkeys(CATEGORIES, 0)

    def add(self, stats: dict[str, np.ndarray]) -> None:
        for c in CATEGORIES:
            self.sums[c] += stats[c]
            if stats[c][4] > 0:
                self.pair_sums[c] += stats[c][:4] / stats[c][4]
                self.pair_counts[c] += 1

    def table(self) -> dict[str, dict[str, dict[str, float]]]:
        per_pair = {}
        for c in CATEGORIES:
            k = self.pair_counts[c]
            values = self.pair_sums[c] / k if k else np.full(4, np.nan)
            per_pair[c] = dict(zip(COLUMNS, map(float, values))) | {"count": k}
        return {"point_weighted": {c: _means(self.sums[c]) for c in CATEGORIES}, "per_pair": per_pair}


def format_table(rows: dict[str, dict[str, dict[str, float]]]) -> str:
    """Plain-text table: one row per name (method or region), EPE/AccS/AccR/Outliers per category."""
    width = 9 * len(COLUMNS)
    lines = [
        f"{'':<16}" + "".join(f"|{c:^{width}}" for c in CATEGORIES),
        f"{'':<16}" + "".join("|" + "".join(f"{k:>9}" for k in COLUMNS) for _ in CATEGORIES),
    ]
    for name, table in rows.items():
        lines.append(
            f"{name:<16}" + "".join("|" + "".join(f"{table[c][k]:>9.4f}" for k in COLUMNS) for c in CATEGORIES)
        )
    return "\n".join(lines)


# ---------------------------------------------------------------- Argoverse 2 (bucketed-scene-flow-eval 2.0.25)

BUCKET_EDGES = np.concatenate([np.linspace(0.0, 2.0, 51), [np.inf]])  # metres per frame
THREEWAY_EDGES = np.array([0.0, 0.05, np.inf])


def av2_bucket_stats(
    pc0,
    pred_flow,
    gt_flow,
    ego1_from_ego0,
    classes,
    ground=None,
    flow_valid=None,
    class_to_meta: dict[int, str] = AV2_META,
    edges: np.ndarray = BUCKET_EDGES,
    metas: tuple[str, ...] = META_CLASSES,
    distance: float = 35.0,
) -> np.ndarray:
    """(len(metas), len(edges) - 1, 3) float64 [epe_sum, speed_sum, count] for one pair.

    Points: non-ground, flow_valid, max(|x|, |y|) < distance in pc0's ego frame, class mapped to a meta-class.
    Speed = ||gt residual flow|| in metres per frame; bucket i holds edges[i] <= speed < edges[i + 1].
    ``classes`` are AV2 flow_labels classes (category index + 1, 0 = none) unless ``class_to_meta`` says otherwise
    (a dataset's ``class_to_meta``; for Threeway use class_to_meta=THREEWAY_META, edges=THREEWAY_EDGES,
    metas=("BACKGROUND", "FOREGROUND")). Sums over pairs add up (point-weighted, as the package's count-weighted
    averages). The package applies its 35 m box to the points it is given (its "global" frame); here it is pc0's ego
    frame, which is what the package sees when its poses are identity.
    """
    truth = PairTruth(pc0, gt_flow, ego1_from_ego0, classes, ground, flow_valid)
    return truth.buckets(class_to_meta, edges, metas, distance).sums(truth.epe(pred_flow))


def _bucket_means(sums: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    with np.errstate(invalid="ignore", divide="ignore"):
        epe = np.where(sums[..., 2] > 0, sums[..., 0] / sums[..., 2], np.nan)
        speed = np.where(sums[..., 2] > 0, sums[..., 1] / sums[..., 2], np.nan)
    return epe, speed


def bucketed_epe(sums: np.ndarray, metas: tuple[str, ...] = META_CLASSES) -> dict:
    """From summed :func:`av2_bucket_stats`: per meta-class (static EPE, dynamic normalised EPE) and their means.

    Static EPE = mean EPE of bucket 0; dynamic = nanmean over buckets 1.. of mean EPE / mean speed of the bucket;
    "mean" = nanmean over meta-classes (empty classes are NaN).
    """
    epe, speed = _bucket_means(sums)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        dynamic = np.nanmean(epe[:, 1:] / speed[:, 1:], axis=1)
        per_class = {m: (float(epe[i, 0]), float(dynamic[i])) for i, m in enumerate(metas)}
        mean = (float(np.nanmean(epe[:, 0])), float(np.nanmean(dynamic)))
    return {"per_class": per_class, "mean": mean}


def threeway_epe(sums: np.ndarray) -> dict[str, float]:
    """From summed :func:`av2_bucket_stats` with edges THREEWAY_EDGES and metas ("BACKGROUND", "FOREGROUND")."""
    epe, _ = _bucket_means(sums)
    out = {
        "foreground_dynamic": float(epe[1, 1]),
        "foreground_static": float(epe[1, 0]),
        "background_static": float(epe[0, 0]),
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return out | {"threeway": float(np.nanmean(list(out.values())))}


THREEWAY_META = {c: ("BACKGROUND" if m == "BACKGROUND" else "FOREGROUND") for c, m in AV2_META.items()}
