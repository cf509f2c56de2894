"""Deprecated, removed in 0.3: the last release's ``icpflow.hardware``, today ``icpflow.core.hardware``."""

from icpflow.core.deprecation import warn_moved
from icpflow.core.hardware import (
    BF16_FLAGS,
    ISA_SWITCHES,
    ONEDNN_ISAS,
    cpu_flags,
    host_line,
    native_bf16,
    onednn_cap,
    torch_bf16_flags,
)

__all__ = [
    "BF16_FLAGS",
    "ISA_SWITCHES",
    "ONEDNN_ISAS",
    "cpu_flags",
    "host_line",
    "native_bf16",
    "onednn_cap",
    "torch_bf16_flags",
]

warn_moved("icpflow.hardware", "icpflow.core.hardware")
