"""What every Hydra entry point shares: label, train, eval and export, each a console script (``icpflow-label``,
``fastflow3d-train``, ``fastflow3d-eval``, ``fastflow3d-export``) and a script of the checkout (``label.py``, ...)
that calls the same ``main``.

* :func:`config_path`: where their configs are, from a checkout (``conf/`` beside the packages: a source tree or an
  editable install) or from an installed wheel (the package :data:`CONFIG_PACKAGE`, ``conf/`` copied by setup.py).
* :func:`hydra_entry`: ``--version`` answered before Hydra reads the command line (Hydra's own flag prints Hydra's
  version), then the Hydra app run through ``icpflow.core.errors_and_signals.run`` (one line and a status for any
  error).

The run folders do not depend on the file that starts a run: each primary config names its job (``hydra.job.name``),
which Hydra would otherwise take from the file holding the task (``cli``).
"""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Callable
from pathlib import Path

from icpflow import __version__
from icpflow.core.errors_and_signals import run

#: the installed copy of the checkout's conf/ (setup.py installs conf/ as this package, for pkg:// in a wheel)
CONFIG_PACKAGE = "icpflow_conf"

#: the checkout's configs: conf/ at the top of the repository, beside the packages
CHECKOUT_CONF = Path(__file__).resolve().parents[1] / "conf"


def config_path() -> str:
    """Hydra's ``config_path`` of every entry point: the checkout's ``conf/`` where this ``icpflow`` is a checkout's,
    else ``pkg://icpflow_conf`` (a wheel). Raises FileNotFoundError (one line) where neither is there."""
    if (CHECKOUT_CONF / "label.yaml").is_file():
        return str(CHECKOUT_CONF)
    if importlib.util.find_spec(CONFIG_PACKAGE) is None:
        raise FileNotFoundError(
            f"no configs: neither {CHECKOUT_CONF} nor the package {CONFIG_PACKAGE} is there; reinstall icpflow"
        )
    return f"pkg://{CONFIG_PACKAGE}"


def version_line(argv0: str) -> str:
    """``<prog> <version>``: the program as it was called (``label.py``, ``icpflow-label``) and ``icpflow``'s
    version, which the whole distribution shares."""
    return f"{os.path.basename(argv0)} {__version__}"


def hydra_entry(prog: str, config_name: str, task: Callable) -> None:
    """Run ``task`` (the body of a Hydra app, taking the composed config) as the entry point ``prog`` with the
    primary config ``config_name``, on the command line (``sys.argv``, as Hydra reads it); ``--version`` anywhere on
    it prints :func:`version_line` and returns instead (exit status 0)."""
    if "--version" in sys.argv[1:]:
        print(version_line(sys.argv[0]))
        return

    def app() -> None:
        import hydra  # here: --version answers without importing Hydra

        hydra.main(version_base="1.3", config_path=config_path(), config_name=config_name)(task)()

    run(prog, app)
