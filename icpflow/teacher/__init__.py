"""The ICP-Flow teacher: ``ICPFlow(cfg)(pc0, pc1, ...)`` with ``ICPFlowConfig`` (see ``pipeline``)."""

__all__ = ["ICPFlow", "ICPFlowConfig", "ICPFlowResult"]


def __getattr__(name: str):
    """Lazy exports: ``icpflow.teacher.config`` (read by every entry point's Hydra config) imports without the
    pipeline's numba kernels."""
    if name == "ICPFlowConfig":
        from icpflow.teacher.config import ICPFlowConfig

        return ICPFlowConfig
    if name in ("ICPFlow", "ICPFlowResult"):
        from icpflow.teacher import pipeline

        return getattr(pipeline, name)
    raise AttributeError(f"module 'icpflow.teacher' has no attribute {name!r}")
