"""Dataset readers. Each converts its format into :class:`icpflow.frames.FramePair` at the boundary."""

from icpflow.datasets.base import PairDataset

__all__ = ["PairDataset"]
