"""Deprecated, removed in 0.3: the last release's ``icpflow.metrics``, today ``icpflow.evaluation.metrics``."""

from icpflow.core.deprecation import warn_moved
from icpflow.evaluation.metrics import (
    AV2_CATEGORIES,
    AV2_META,
    BUCKET_EDGES,
    CATEGORIES,
    COLUMNS,
    META_CLASSES,
    RELATIVE_EPS,
    THREEWAY_EDGES,
    THREEWAY_META,
    Buckets,
    MetricAccumulator,
    PairTruth,
    PaperSplits,
    av2_bucket_stats,
    bucketed_epe,
    format_table,
    frame_pair_stats,
    pair_stats,
    threeway_epe,
)

__all__ = [
    "AV2_CATEGORIES",
    "AV2_META",
    "BUCKET_EDGES",
    "Buckets",
    "CATEGORIES",
    "COLUMNS",
    "META_CLASSES",
    "MetricAccumulator",
    "PairTruth",
    "PaperSplits",
    "RELATIVE_EPS",
    "THREEWAY_EDGES",
    "THREEWAY_META",
    "av2_bucket_stats",
    "bucketed_epe",
    "format_table",
    "frame_pair_stats",
    "pair_stats",
    "threeway_epe",
]

warn_moved("icpflow.metrics", "icpflow.evaluation.metrics")
