"""What every entry point (``label.py``, ``train.py``, ``export.py``, ``eval.py``, ``fastflow3d-infer``) does with an
error or a signal: one line on stderr, ``<prog>: <option or file>: <cause>; <fix>``, and an exit status; the
traceback only with ``HYDRA_FULL_ERROR=1``.

Exit statuses: 0 done; 1 partial results (each script says when); 2 bad input or a fault (a wrong option or type, an
unreadable file, a full or read-only disk); 128 + N stopped by signal N (130 Ctrl-C / SIGINT, 143 SIGTERM).

* :func:`reported` (around the body of the ``@hydra.main`` function) and :func:`run` (around the call of that
  function, for Hydra's own errors: a bad override, an output folder it cannot create) turn whatever escapes into
  that line and status; :func:`exit_status` is :func:`reported` for a command that returns its status
  (``fastflow3d-infer``, ``run_export``).
* A config's options are checked by its schema (``icpflow.core.settings``): Hydra's error about a value of the wrong
  type or an unknown option becomes one line naming it (:func:`error_line`), and so does an
  :class:`~icpflow.core.settings.OptionError`.
* One way to stop: :func:`on_signals` is the only place that installs handlers for :data:`STOP_SIGNALS` (the entry
  points through :func:`stop_on_signals`, training's ``fastflow3d.training.callbacks.LastCheckpoint`` to note a signal
  and stop after the current step); :func:`signals_held` only holds them back around a call that must not be
  interrupted, and delivers them to those handlers after it. :class:`Stop` is a signal turned into an exception; it
  carries the line that says what was kept and how to go on, and its exit status (:func:`stop_signum` also reads a
  bare ``KeyboardInterrupt``).
* :func:`one_line` is the one way to fold a message (an exception's text) onto one line.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator

from icpflow.core.settings import OptionError, type_error_line
from icpflow.core.stops import (  # noqa: F401 - the names every entry point used from here
    STOP_SIGNALS,
    STOPS,
    Stop,
    raise_stop_behind,
    signal_words,
    stop_behind,
    stop_signum,
    stopped_by,
)

FULL_ERROR = "HYDRA_FULL_ERROR"  # set (to 1) by the user: tracebacks as Python and Hydra print them
MARKER = "ICPFLOW_ENTRY"  # set by :func:`run` with HYDRA_FULL_ERROR=1: Hydra raises to us, no traceback was asked

#: what to do about an OSError, by errno
FIXES = {
    errno.ENOSPC: "free space there or write elsewhere",
    errno.EDQUOT: "free space there or write elsewhere",
    errno.EROFS: "write to a writable place",
    errno.EACCES: "fix its permissions or write elsewhere",
    errno.EPERM: "fix its permissions or write elsewhere",
    errno.ENOENT: "check the path",
    errno.ENOTDIR: "check the path: a part of it is a file",
    errno.EISDIR: "give a file, not a folder",
}


def on_signals(handle: Callable[[int], None], signums=STOP_SIGNALS) -> Callable[[], None]:
    """Route each signal of ``signums`` that reaches this process to ``handle(signum)`` (which raises :class:`Stop`,
    or notes the signal to stop later); returns the function that puts the previous handlers back.

    The one place where entry points and the training callback install signal handlers. A process forked from this
    one (a DataLoader or a library's worker, which Ctrl-C or a scheduler signals with it) ignores these signals: its
    owner ends it when it stops. A SIGINT ignored when this is called (a background job of a shell script) stays
    ignored, as Python leaves it. Outside the main thread nothing is installed (signals reach the main thread). A stop
    that ``handle`` raises is noted (:func:`stops_raised`)."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    owner = os.getpid()
    raised = next((stops_raised(h) for h in map(signal.getsignal, signums) if stops_raised(h) is not None), [])

    def route(signum, frame) -> None:
        if os.getpid() == owner:
            try:
                handle(signum)
            except BaseException:
                raised.append(signum)
                raise

    route.raised = raised
    previous = {}
    for signum in signums:
        if signum == signal.SIGINT and signal.getsignal(signum) is signal.SIG_IGN:
            continue
        previous[signum] = signal.signal(signum, route)

    def restore() -> None:
        while previous:
            signum, handler = previous.popitem()
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)  # None: installed outside Python

    return restore


def stops_raised(handler) -> list[int] | None:
    """The signals for which a handler that :func:`on_signals` installed raised a stop (in arrival order), or None for
    any other handler. Nested :func:`on_signals` note into the outermost one's list, so an entry point
    (``icpflow.core.launch.launched``) learns of every stop raised in its command, also of one that a library
    swallowed: Hydra's ``get_mode`` (``except Exception`` over omegaconf's error raised over the stop), a Cython
    module's import (its ABC registrations ignore every error), :func:`raise_swallowed_stop`."""
    return getattr(handler, "raised", None)


def raise_swallowed_stop() -> None:
    """Raise again, as a :class:`Stop`, a stop that a handler of :func:`on_signals` raised and that did not end the
    run (a library swallowed it: :func:`stops_raised`). Called where the run goes on to long work (the start of
    :func:`stop_on_signals`, after the kernels' first import), never while a stop unwinds."""
    for signum in STOP_SIGNALS:
        raised = stops_raised(signal.getsignal(signum))
        if raised:
            raise Stop(raised[0])


def raise_stop(signum: int) -> None:
    """The handler of :func:`stop_on_signals`: stop now."""
    raise Stop(signum)


def ignore_stop_signals() -> None:
    """From now on the stop signals are ignored: for the moments of a process's exit, once its status is known."""
    for signum in STOP_SIGNALS:
        signal.signal(signum, signal.SIG_IGN)


@contextlib.contextmanager
def stop_on_signals(signums=STOP_SIGNALS) -> Iterator[None]:
    """Within the block, the signals raise :class:`Stop` in this process (so ``finally`` blocks, atomic writers and
    worker pools clean up), as :func:`on_signals` routes them; the previous handlers come back after it."""
    restore = on_signals(raise_stop, signums)
    try:
        raise_swallowed_stop()
        yield
    finally:
        restore()


@contextlib.contextmanager
def signals_held(signums=STOP_SIGNALS) -> Iterator[None]:
    """Hold the signals back for the block and deliver them after it, to the handlers installed before it: around a
    library call that runs its own threads on the call's memory (scipy's ``cKDTree.query`` with ``workers``). A
    :class:`Stop` or ``KeyboardInterrupt`` raised inside such a call unwinds it while its threads still write into
    what it allocated: a segmentation fault, seen after a Ctrl-C of ``label.py`` (the call's own join of its
    threads is where the signal lands). Outside the main thread nothing is held (signals reach the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    arrived: list[int] = []
    previous = {signum: signal.signal(signum, lambda signum, frame: arrived.append(signum)) for signum in signums}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)  # None: installed outside Python
        for signum in dict.fromkeys(arrived):
            signal.raise_signal(signum)


# ---------------------------------------------------------------------------------------------------- messages


def one_line(text: object) -> str:
    """``text`` (a message, an exception) on one line: its runs of white space, newlines included, as one space."""
    return " ".join(str(text).split())


def os_error_line(error: OSError, fix: str | None = None) -> str:
    """``<file>: <cause>; <fix>`` for an OSError (``icpflow.core.atomic.WriteError`` included: its message already names
    the file; the errno is that of the error it replaced)."""
    cause = error
    while cause.errno is None and isinstance(cause.__cause__ or cause.__context__, OSError):
        cause = cause.__cause__ or cause.__context__
    if error.errno is None and error.filename is None:  # a message of ours (WriteError): already "<file>: ..."
        text = one_line(error)
    else:
        target = " -> ".join(str(name) for name in (error.filename, error.filename2) if name is not None)
        text = f"{target}: {error.strerror or one_line(error)}" if target else one_line(error)
    fix = fix or FIXES.get(cause.errno)
    return f"{text}; {fix}" if fix else text


def tilde_hint(text: str) -> str:
    """How to write the override with ``~`` that Hydra's grammar refused in ``text`` (``key=~/x ^ ...``): its value
    in Hydra's quotes, the whole in the shell's."""
    override = text.split("LexerNoViableAltException: ", 1)[-1].split(" ^", 1)[0].strip()
    key, _, value = override.partition("=")
    if not key or not value:
        return "a path with ~ is quoted for Hydra: \"out_dir='~/x'\""
    return f"a path with ~ is quoted for Hydra: \"{key}='{value}'\""


def error_line(error: BaseException, expected: tuple[type[BaseException], ...] = ()) -> str:
    """One line for an exception that escaped an entry point: the message of an ``expected`` (one-line) error or an
    :class:`OptionError` as it is; an OSError as :func:`os_error_line`; Hydra's and OmegaConf's errors (a bad
    override, a missing value) by their first lines; anything else as unexpected, pointing at ``HYDRA_FULL_ERROR``."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    if isinstance(error, (OptionError, *expected)):
        return one_line(error)
    if isinstance(error, OSError):
        return os_error_line(error)
    if isinstance(error, (HydraException, OmegaConfBaseException)):
        line = type_error_line(error)  # a value of the wrong type, an unknown option (the schemas)
        if line is not None:
            return f"{line}; see `--help` and `--cfg job` for the options"
        text = one_line(str(error).split("\n    full_key:")[0])
        if "LexerNoViableAltException" in text and "~" in text:  # Hydra's grammar has no bare ~; a quoted one is a path
            text = f"{text} ({tilde_hint(text)})"
        cause = error.__cause__
        if isinstance(cause, OmegaConfBaseException):
            text = f"{text} ({one_line(str(cause).split('full_key:')[0])})"
        return f"{text}; see `--help` and `--cfg job` for the options"
    first = str(error).strip().splitlines()[0] if str(error).strip() else ""
    return f"unexpected {type(error).__name__}: {first} (set {FULL_ERROR}=1 for the traceback)"


# ---------------------------------------------------------------------------------------------------- running


def _full_error_asked() -> bool:
    return os.environ.get(FULL_ERROR, "") not in ("", "0") and MARKER not in os.environ


@contextlib.contextmanager
def stops_unprinted() -> Iterator[None]:
    """Within the block, a stop that Python or a compiled module prints instead of raising prints nothing: the stop
    becomes the entry point's one line (:func:`~icpflow.core.launch.launched` ends a command whose stop was
    swallowed as stopped). Where: a compiled module's import calls ``PyErr_Print`` (``sys.excepthook``), then raises
    an ImportError in the stop's place; a signal's handler that runs inside a callback Python cannot raise from (a
    weakref's, as importlib's module locks have; a finaliser) is "ignored" (``sys.unraisablehook``). Every other
    exception prints as before."""
    previous, previous_unraisable = sys.excepthook, sys.unraisablehook

    def hook(kind, value, traceback) -> None:
        if not isinstance(value, (Stop, KeyboardInterrupt)):
            previous(kind, value, traceback)

    def unraisable(report) -> None:
        if not isinstance(report.exc_value, (Stop, KeyboardInterrupt)):
            previous_unraisable(report)

    sys.excepthook, sys.unraisablehook = hook, unraisable
    try:
        yield
    finally:
        sys.excepthook, sys.unraisablehook = previous, previous_unraisable


@contextlib.contextmanager
def reported(prog: str, *expected: type[BaseException]) -> Iterator[None]:
    """An exception that escapes the block becomes one line on stderr, ``<prog>: ...``, and an exit status (module
    docstring); with ``HYDRA_FULL_ERROR=1`` set by the user it propagates with its traceback. ``expected``: exception
    types whose message is the line to print. Used inside the ``@hydra.main`` function (so Hydra adds nothing) and,
    by :func:`run`, around it (Hydra's own errors)."""
    full = _full_error_asked()
    try:
        try:
            with stops_unprinted():
                yield
        except Exception as error:  # a stop inside compiled code or a library, as another error: the stop behind it
            raise_stop_behind(error)
            raise
    except Stop as stop:
        if launching_process():  # the ranks a launcher started beside it stop with it, silently
            print(f"{prog}: {one_line(stop)}", file=sys.stderr)
        sys.exit(stop.status)
    except KeyboardInterrupt:
        print(f"{prog}: {signal_words(signal.SIGINT)}", file=sys.stderr)
        sys.exit(128 + signal.SIGINT)
    except Exception as error:
        if full:
            raise
        print(f"{prog}: {error_line(error, expected)}", file=sys.stderr)
        sys.exit(2)


def launching_process() -> bool:
    """Whether this is the process a user started, not a rank that a data-parallel launcher (Lightning's DDP,
    torchrun, SLURM's srun) started beside it: every rank variable they set is unset or 0."""
    ranks = (os.environ.get(name, "0") for name in ("LOCAL_RANK", "NODE_RANK", "SLURM_PROCID", "RANK"))
    return all(rank in ("", "0") for rank in ranks)


def run(prog: str, hydra_main: Callable[[], object]) -> None:
    """Call ``hydra_main`` (a ``@hydra.main`` function whose body is in :func:`reported`), reporting Hydra's own
    errors (a bad override, an output folder it cannot create) the same way. Hydra is asked to raise them
    (``HYDRA_FULL_ERROR=1`` and :data:`MARKER` set for the call) instead of printing its multi-line report."""
    asked = FULL_ERROR in os.environ
    if not asked:
        os.environ[FULL_ERROR], os.environ[MARKER] = "1", prog
    try:
        with reported(prog):
            hydra_main()
    finally:
        if not asked:
            os.environ.pop(FULL_ERROR, None)
            os.environ.pop(MARKER, None)


def exit_status(prog: str, body: Callable[[], int | None], *expected: type[BaseException]) -> int:
    """``body()`` inside :func:`reported` for a command that returns its exit status instead of exiting (the
    ``fastflow3d-infer`` console script, ``fastflow3d.artifact.export.run_export``; tests call them): ``body``'s status
    (None: 0), or the status of the line :func:`reported` printed."""
    try:
        with reported(prog, *expected):
            return int(body() or 0)
    except SystemExit as stopped:
        code = stopped.code
        return code if isinstance(code, int) else 0 if code is None else 1
