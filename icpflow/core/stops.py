"""What a stop is (a stop signal turned into an exception) and how to find one that arrived as another error.

A signal's handler (``icpflow.core.errors_and_signals.on_signals``) raises :class:`Stop` (or Python's own
``KeyboardInterrupt`` for Ctrl-C); where it runs inside compiled code the stop surfaces as a ``SystemError`` or an
``ImportError`` instead (:func:`stop_behind`). Every ``except Exception`` of the packages (a bad sample skipped, an
optional import's fallback, a damaged file reported) starts with :func:`raise_stop_behind`, so that no stop is taken
for an error. Imports nothing of the project: every module may use it.
"""

from __future__ import annotations

import signal
import sys

#: the signals that stop a run: Ctrl-C (SIGINT) and a scheduler's or supervisor's SIGTERM
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Stop(BaseException):
    """A signal asked the run to stop (a BaseException, so that no ``except Exception`` swallows it).

    ``str(stop)`` is the line to print: what happened, what was kept, how to go on; exit status 128 + ``signum``.
    """

    def __init__(self, signum: int, message: str | None = None):
        self.signum = int(signum)
        super().__init__(message or signal_words(signum))

    @property
    def status(self) -> int:
        return 128 + self.signum


def signal_words(signum: int) -> str:
    """``interrupted (SIGINT)`` / ``terminated (SIGTERM)`` / ``stopped (SIGHUP)``."""
    name = signal.Signals(signum).name
    verb = {"SIGINT": "interrupted", "SIGTERM": "terminated"}.get(name, "stopped")
    return f"{verb} ({name})"


def stop_signum(interrupt: BaseException) -> int:
    """The signal that stopped a run: a :class:`Stop`'s, SIGINT for a bare ``KeyboardInterrupt`` (Ctrl-C where no
    handler of ``icpflow.core.errors_and_signals.on_signals`` was installed: outside the main thread, or before it)."""
    return interrupt.signum if isinstance(interrupt, Stop) else int(signal.SIGINT)


#: what a stop can arrive as: a Stop or KeyboardInterrupt raised by a signal's handler, or another error raised over
#: it where the handler ran inside compiled code (:func:`stop_behind`); :func:`stopped_by` tells them apart
STOPS = (Stop, KeyboardInterrupt, SystemError, ImportError)


def stop_behind(error: BaseException) -> BaseException | None:
    """The stop (a :class:`Stop` or ``KeyboardInterrupt``) that ``error`` is or was raised over, or None.

    A signal whose handler runs inside compiled code surfaces as another error: where a numba kernel returns, a
    ``SystemError(CPUDispatcher(...) returned a result with an exception set)`` caused by the stop; where a compiled
    module imports a module of its own (numba's first import, numpy's ``import_array``), an ``ImportError``
    (``numba._devicearray failed to import``) raised after the module printed the stop, which Python keeps as
    ``sys.last_value``."""
    seen = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, (Stop, KeyboardInterrupt)):
            return error
        if _printed_in_place_of_a_stop(error):
            return sys.last_value
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return None


def _printed_in_place_of_a_stop(error: BaseException) -> bool:
    """Whether ``error`` is the ImportError that a compiled module's import raises after it printed a stop
    (``PyErr_Print``, then ``<module> failed to import`` with no cause: numba's ``_devicearray``, numpy's
    ``import_array``): the stop it printed is ``sys.last_value``. Any other ImportError (a missing package, one raised
    over another error) is not, whatever an interactive session printed before."""
    printed = getattr(sys, "last_value", None)
    return (
        isinstance(error, ImportError)
        and "failed to import" in str(error)
        and error.__cause__ is None
        and error.__context__ is None
        and isinstance(printed, (Stop, KeyboardInterrupt))
    )


def raise_stop_behind(error: BaseException) -> None:
    """Raise the stop behind ``error`` (:func:`stop_behind`), if any: where a bad sample is recorded and skipped
    (``except Exception``), a Ctrl-C or SIGTERM inside compiled code must stop the run instead."""
    stop = stop_behind(error)
    if stop is not None:
        raise stop from None


def stopped_by(error: BaseException) -> BaseException:
    """The stop behind ``error`` (:func:`stop_behind`); ``error`` itself is raised again where it is not a stop."""
    stop = stop_behind(error)
    if stop is None:
        raise error
    return stop
