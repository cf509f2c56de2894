"""The last release's paths that moved, kept importable for one more release with a ``DeprecationWarning`` that names
today's path (the modules of ``fastflow3d`` that now live in its rooms, and the renamed ``icpflow.entry`` and
``icpflow.teacher.tracker``).

An old module path is a tiny module at that path (a *shim*) that re-exports today's objects under their old names and
calls :func:`warn_moved` once, when it is first imported; an old module that became a package of the same name (its
names now in the package's modules) answers them from its ``__getattr__`` with :func:`moved_attribute`. Both go in
:data:`REMOVAL`. Only the standard library is imported here: every shim, and ``icpflow`` itself, may import it.
"""

from __future__ import annotations

import importlib
import warnings

#: the release that removes the old paths
REMOVAL = "0.3"

#: icpflow's moved modules whose objects a stored or hand-written config names as ``_target_`` (a dataset's reader):
#: old module -> module today, read by :func:`current_target` (``icpflow.datasets.from_config``; a checkpoint's
#: stored config: ``fastflow3d.artifact.checkpoint.MOVED_TARGETS``)
MOVED_TARGETS = {"icpflow.datasets.sequence": "icpflow.datasets.scan_folder"}


def current_target(target, moved: dict[str, str]):
    """``target`` (``module.name``) named by today's module where its module moved (``moved``: old -> new); any
    other value as it is."""
    module, _, name = target.rpartition(".") if isinstance(target, str) else ("", "", "")
    return f"{moved[module]}.{name}" if module in moved else target


def moved_message(old: str, new: str, instead: str | None = None) -> str:
    """``<old> is deprecated and will be removed in 0.3; use <new>`` (``instead``: a shorter way, in brackets)."""
    hint = f" (or: {instead})" if instead else ""
    return f"{old} is deprecated and will be removed in {REMOVAL}; use {new}{hint}"


def warn_moved(old: str, new: str, instead: str | None = None) -> str:
    """The ``DeprecationWarning`` of the shim of module ``old``, called from the shim's body; returns its message.

    It points at the importer: stacklevel 3 is this function, the shim's body, then the frame that imported it
    (``warnings`` skips the import machinery's own frames in between)."""
    message = moved_message(old, new, instead)
    warnings.warn(message, DeprecationWarning, stacklevel=3)
    return message


def moved_attribute(package: str, name: str, homes: dict[str, str]):
    """``name`` of the old module ``package`` (now a package) from the module ``homes[name]`` where it lives today,
    with a ``DeprecationWarning`` at each look-up; an AttributeError for a name the old module did not have, as a
    module's ``__getattr__`` must (stacklevel 3: this function, the package's ``__getattr__``, its caller)."""
    home = homes.get(name)
    if home is None:
        raise AttributeError(f"module {package!r} has no attribute {name!r}")
    warnings.warn(moved_message(f"{package}.{name}", f"{home}.{name}"), DeprecationWarning, stacklevel=3)
    return getattr(importlib.import_module(home), name)
