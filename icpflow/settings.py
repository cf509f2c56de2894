"""Deprecated, removed in 0.3: the last release's ``icpflow.settings``, today ``icpflow.core.settings``."""

from icpflow.core.deprecation import warn_moved
from icpflow.core.settings import (
    HYDRA_KEYS,
    RULES,
    OptionError,
    accepts,
    broken_rule,
    check_config,
    check_target_arguments,
    expand_home,
    setting,
    signature_schema,
    store,
    type_error_line,
    type_words,
    unknown_words,
)

__all__ = [
    "HYDRA_KEYS",
    "OptionError",
    "RULES",
    "accepts",
    "broken_rule",
    "check_config",
    "check_target_arguments",
    "expand_home",
    "setting",
    "signature_schema",
    "store",
    "type_error_line",
    "type_words",
    "unknown_words",
]

warn_moved("icpflow.settings", "icpflow.core.settings")
