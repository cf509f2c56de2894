"""Dataset readers. Each converts its format into :class:`icpflow.core.frame_pair.FramePair` at the boundary."""

from icpflow.datasets.base import PairDataset

__all__ = ["PairDataset"]
