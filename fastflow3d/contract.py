"""Deprecated, removed in 0.3: the last release's ``fastflow3d.contract``, today ``fastflow3d.network.contract``."""

from fastflow3d.network.contract import VERSION, ContractError, InputContract, PreparedPair, read_grid, upgrade
from icpflow.core.deprecation import warn_moved

__all__ = ["VERSION", "ContractError", "InputContract", "PreparedPair", "read_grid", "upgrade"]

warn_moved("fastflow3d.contract", "fastflow3d.network.contract")
