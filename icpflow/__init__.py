"""icpflow: the ICP-Flow teacher, dataset readers, pseudo-label shards and scene-flow metrics."""

from icpflow.core.frame_pair import FramePair, FramePairError, FrameSequence
from icpflow.core.kernel_cache import choose_kernel_cache

__version__ = "0.2.0"

choose_kernel_cache()  # before any kernel is defined: a read-only install and home still run

__all__ = ["FramePair", "FramePairError", "FrameSequence", "ICPFlow", "ICPFlowConfig", "__version__"]


def __getattr__(name: str):
    """Lazy exports: ``from icpflow import ICPFlow, ICPFlowConfig`` without importing the teacher on
    ``import icpflow``."""
    if name in ("ICPFlow", "ICPFlowConfig"):
        from icpflow import teacher

        return getattr(teacher, name)
    raise AttributeError(f"module 'icpflow' has no attribute {name!r}")
