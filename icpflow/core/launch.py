"""The first moments of every entry point: its command is imported (torch, numba, Hydra: seconds) only inside
:func:`launched`, so that a Ctrl-C or a SIGTERM while it loads ends as one at any other moment, one line and exit
128 + the signal, instead of Python's traceback or an end by the signal. Each console script and checkout script
starts from a light module (``launch``) of its room whose functions call :func:`launched` with the command's real
``main``."""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable

from icpflow.core.errors_and_signals import (
    Stop,
    ignore_stop_signals,
    on_signals,
    raise_stop,
    signal_words,
    stop_signum,
)


def launched(prog: str, load: Callable[[], Callable], *args, exits: bool = True):
    """``load()()`` with ``args``: ``load`` imports and returns the command's ``main``.

    A stop signal (SIGINT, SIGTERM) while it loads is noted until the import is done (a library's import may turn a
    KeyboardInterrupt into an error of its own: omegaconf does), then is the line ``<prog>: interrupted (SIGINT)
    while starting; nothing was done`` (``terminated (SIGTERM)``) and exit status 128 + the signal. One that lands in
    ``main`` outside its own report (while it parses its options) is ``<prog>: interrupted (SIGINT)`` and 130, or
    ``terminated (SIGTERM)`` and 143. Where the process ends after ``main`` (``exits``), a signal once ``main`` has
    returned is ignored: the exit status is ``main``'s."""
    main = _loaded(prog, load)
    restore = on_signals(raise_stop, (signal.SIGTERM,))  # SIGINT is Python's KeyboardInterrupt already
    try:
        return main(*args)
    except (KeyboardInterrupt, Stop) as stop:  # before or after the command's own report
        print(f"{prog}: {stop if isinstance(stop, Stop) else signal_words(signal.SIGINT)}", file=sys.stderr)
        raise SystemExit(128 + stop_signum(stop)) from None
    finally:
        restore()
        if exits:  # what follows is the interpreter's exit, where Python restores the default SIGINT action: a
            # signal there would end the process by the signal instead of with the status just given
            ignore_stop_signals()


def _loaded(prog: str, load: Callable[[], Callable]) -> Callable:
    """``load()``, the stop signals that arrive meanwhile noted; the first of them ends the process in one line."""
    arrived: list[int] = []
    restore = on_signals(arrived.append)
    try:
        main = load()
    except KeyboardInterrupt:  # one that came before the handlers
        arrived.append(int(signal.SIGINT))
    finally:
        restore()
    if arrived:
        print(f"{prog}: {signal_words(arrived[0])} while starting; nothing was done", file=sys.stderr)
        raise SystemExit(128 + arrived[0])
    return main
