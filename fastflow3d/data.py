"""Deprecated, removed in 0.3: the last release's ``fastflow3d.data``, today ``fastflow3d.training.data``."""

from fastflow3d.training.data import (
    GT_KEYS,
    PER_POINT0,
    PER_POINT1,
    DataError,
    Draw,
    EpochOrder,
    NetworkCrop,
    ShardDataModule,
    StudentDataset,
    collate,
    init_worker,
    labeller_contract,
    split_samples,
)
from icpflow.core.deprecation import warn_moved

__all__ = [
    "GT_KEYS",
    "PER_POINT0",
    "PER_POINT1",
    "DataError",
    "Draw",
    "EpochOrder",
    "NetworkCrop",
    "ShardDataModule",
    "StudentDataset",
    "collate",
    "init_worker",
    "labeller_contract",
    "split_samples",
]

warn_moved("fastflow3d.data", "fastflow3d.training.data")
