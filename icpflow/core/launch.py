"""The first moments of every entry point: its command is imported (torch, numba, Hydra: seconds) only inside
:func:`launched`, so that a Ctrl-C while it loads ends as one at any other moment, one line and exit 130, instead of
Python's traceback. Each console script and checkout script starts from a light module (``launch``) of its room
whose functions call :func:`launched` with the command's real ``main``."""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable

from icpflow.core.errors_and_signals import signal_words, signals_held


def launched(prog: str, load: Callable[[], Callable], *args, exits: bool = True):
    """``load()()`` with ``args``: ``load`` imports and returns the command's ``main``. A Ctrl-C while it loads is
    held until the import is done (a library's import may turn a KeyboardInterrupt into an error of its own: omegaconf
    does), then is the line ``<prog>: interrupted (SIGINT) while starting; nothing was done`` and exit status 130; one
    that ``main`` lets through (outside its own report: while it parses its options) is ``<prog>: interrupted
    (SIGINT)`` and 130.
    Where the process ends after ``main`` (``exits``), a Ctrl-C once ``main`` has returned is ignored: the exit status
    is ``main``'s."""
    try:
        with signals_held():
            main = load()
    except KeyboardInterrupt:
        print(f"{prog}: {signal_words(signal.SIGINT)} while starting; nothing was done", file=sys.stderr)
        raise SystemExit(128 + signal.SIGINT) from None
    try:
        return main(*args)
    except KeyboardInterrupt:  # before or after the command's own report (its option parsing, its last line)
        print(f"{prog}: {signal_words(signal.SIGINT)}", file=sys.stderr)
        raise SystemExit(128 + signal.SIGINT) from None
    finally:
        if exits:  # what follows is the interpreter's exit, where Python restores the default SIGINT action: a
            # Ctrl-C there would end the process by the signal instead of with the status just given
            signal.signal(signal.SIGINT, signal.SIG_IGN)
