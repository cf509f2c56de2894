"""Scoring: one pair's point selection made once (:class:`PairScorer`), every method's statistics on it, and the
running sums of each method (:class:`MethodScores`).

Statistics are those of ``icpflow.evaluation.metrics``: the ICP-Flow paper's splits (point-weighted and per pair), the
AV2 Threeway EPE, the bucketed normalised EPE (when the dataset maps its classes to AV2 meta-classes), seconds per pair
and the real dt of the pairs. The ground-truth side of a pair (residual flow, kept points, splits, buckets) is
computed once per pair and shared by every method; each method's prediction costs one EPE and three sums.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from icpflow.core.frame_pair import FramePair
from icpflow.evaluation import metrics


@dataclass
class MetricOptions:
    """How pairs are scored: ``crop`` half-width of the xy box (m, None = all), ground, relative error base,
    ``class_to_meta`` (dataset classes -> AV2 meta-classes; None: no bucketed EPE, Threeway foreground = class > 0)."""

    crop: float | None = 32.0
    include_ground: bool = False
    relative_to: str = "residual"
    dynamic_speed: float = 0.5
    class_to_meta: dict[int, str] | None = None

    def settings(self) -> dict:
        """What metrics.json records of these options."""
        return {
            "crop": self.crop,
            "include_ground": self.include_ground,
            "relative_to": self.relative_to,
            "dynamic_speed": self.dynamic_speed,
            "bucketed_classes": self.class_to_meta is not None,
        }


@dataclass(frozen=True)
class PairScores:
    """One method on one pair: ``paper`` {category: (5,) sums}, ``threeway`` (2, 2, 3) and ``buckets`` (metas,
    buckets, 3) or None (``icpflow.evaluation.metrics`` sums), ``seconds`` the method took, ``dt`` (s) of the pair."""

    paper: dict[str, np.ndarray]
    threeway: np.ndarray
    buckets: np.ndarray | None
    seconds: float
    dt: float


class PairScorer:
    """The ground-truth side of one pair, selected once: :meth:`score` turns any method's flow into its
    :class:`PairScores`. Raises ValueError for a pair without ground-truth flow and classes."""

    def __init__(self, pair: FramePair, options: MetricOptions):
        self.pair = pair
        self.truth = truth = metrics.PairTruth.of_pair(pair, options.include_ground)
        self.paper = truth.paper(pair.dt, options.crop, options.dynamic_speed, options.relative_to)
        if options.class_to_meta is None:
            threeway_meta = {0: "BACKGROUND"} | {int(c): "FOREGROUND" for c in np.unique(pair.classes) if c > 0}
            self.buckets = None
        else:
            threeway_meta = {
                c: "BACKGROUND" if m == "BACKGROUND" else "FOREGROUND" for c, m in options.class_to_meta.items()
            }
            self.buckets = truth.buckets(options.class_to_meta)
        self.threeway = truth.buckets(threeway_meta, metrics.THREEWAY_EDGES, ("BACKGROUND", "FOREGROUND"))

    def score(self, flow: np.ndarray, seconds: float) -> PairScores:
        """The statistics of FULL ``flow`` (N0, 3) on this pair (raises ValueError on a wrong shape)."""
        epe = self.truth.epe(flow)
        buckets = self.buckets.sums(epe) if self.buckets is not None else None
        return PairScores(self.paper.sums(epe), self.threeway.sums(epe), buckets, seconds, float(self.pair.dt))


@dataclass
class MethodScores:
    """Running sums of one method over the pairs seen so far."""

    paper: metrics.MetricAccumulator = field(default_factory=metrics.MetricAccumulator)
    buckets: np.ndarray | None = None
    threeway: np.ndarray | None = None
    seconds: list[float] = field(default_factory=list)
    dts: list[float] = field(default_factory=list)

    def add(self, scores: PairScores) -> None:
        self.paper.add(scores.paper)
        self.threeway = scores.threeway if self.threeway is None else self.threeway + scores.threeway
        if scores.buckets is not None:
            self.buckets = scores.buckets if self.buckets is None else self.buckets + scores.buckets
        self.seconds.append(scores.seconds)
        self.dts.append(scores.dt)

    def summary(self) -> dict:
        """{"paper": {"point_weighted"|"per_pair": {category: row}}, "pairs", "seconds_per_pair" (median), "dt_s"
        (mean seconds between the scans of the pairs), "threeway", "bucketed" (None without meta-classes)}."""
        out = {
            "paper": self.paper.table(),
            "pairs": len(self.seconds),
            "seconds_per_pair": float(np.median(self.seconds)) if self.seconds else math.nan,
            "dt_s": float(np.mean(self.dts)) if self.dts else math.nan,
        }
        out["threeway"] = metrics.threeway_epe(self.threeway) if self.threeway is not None else None
        if self.buckets is not None:
            bucketed = metrics.bucketed_epe(self.buckets)
            out["bucketed"] = {
                "per_class": {
                    k: {"static_epe": s, "dynamic_normalized_epe": d} for k, (s, d) in bucketed["per_class"].items()
                },
                "mean": {"static_epe": bucketed["mean"][0], "dynamic_normalized_epe": bucketed["mean"][1]},
            }
        else:
            out["bucketed"] = None
        return out
