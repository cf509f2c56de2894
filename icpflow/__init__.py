"""icpflow: the ICP-Flow teacher, dataset readers, pseudo-label shards and scene-flow metrics."""

from icpflow.frames import FramePair, FramePairError, FrameSequence

__version__ = "0.1.0"

__all__ = ["FramePair", "FramePairError", "FrameSequence", "__version__"]
