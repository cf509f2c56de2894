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
    stops_raised,
    stops_unprinted,
)


def launched(prog: str, load: Callable[[], Callable], *args, exits: bool = True):
    """``load()()`` with ``args``: ``load`` imports and returns the command's ``main``.

    A stop signal (SIGINT, SIGTERM) while it loads is noted until the import is done (a library's import may turn a
    KeyboardInterrupt into an error of its own: omegaconf does), then is the line ``<prog>: interrupted (SIGINT)
    while starting; nothing was done`` (``terminated (SIGTERM)``) and exit status 128 + the signal. One that lands in
    ``main`` outside its own report (while it parses its options) is ``<prog>: interrupted (SIGINT)`` and 130, or
    ``terminated (SIGTERM)`` and 143. A stop raised in ``main`` that a library swallowed (``stops_raised``) ends it
    as stopped where the command's work would start (``stop_on_signals``), or else after ``main``: its line and
    128 + the signal in place of the status ``main`` gave. Where the process ends after ``main`` (``exits``), a
    signal once ``main`` has returned is ignored: the exit status is ``main``'s."""
    main = _loaded(prog, load)
    restore = on_signals(_raise_in_main)
    raised = stops_raised(signal.getsignal(signal.SIGTERM))  # None outside the main thread: nothing installed
    raised = [] if raised is None else raised
    try:
        try:
            with stops_unprinted():
                status = main(*args)
        except SystemExit as done:
            _stop_kept(prog, raised, done.code)
            raise
        _stop_kept(prog, raised, status)
        return status
    except (KeyboardInterrupt, Stop) as stop:  # before or after the command's own report
        print(f"{prog}: {stop if isinstance(stop, Stop) else signal_words(signal.SIGINT)}", file=sys.stderr)
        raise SystemExit(128 + stop_signum(stop)) from None
    finally:
        restore()
        if exits:  # what follows is the interpreter's exit, where Python restores the default SIGINT action: a
            # signal there would end the process by the signal instead of with the status just given
            ignore_stop_signals()


def _raise_in_main(signum: int) -> None:
    """A stop signal in the command: Ctrl-C as Python's own KeyboardInterrupt, another as :class:`Stop`."""
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise_stop(signum)


def _stop_kept(prog: str, raised: list[int], status: object) -> None:
    """A command that ends with another status than 128 + a stop raised in it lost that stop (a library swallowed
    it, or reported the error raised over it): the process ends as stopped, in its line."""
    if raised and status not in {128 + signum for signum in raised}:
        print(f"{prog}: {signal_words(raised[0])}", file=sys.stderr)
        raise SystemExit(128 + raised[0])


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
