"""The ICP-Flow teacher: ``ICPFlow(cfg)(pc0, pc1, ...)`` with ``ICPFlowConfig`` (see ``pipeline``)."""

from icpflow.teacher.config import ICPFlowConfig
from icpflow.teacher.pipeline import ICPFlow, ICPFlowResult

__all__ = ["ICPFlow", "ICPFlowConfig", "ICPFlowResult"]
