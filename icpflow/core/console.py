"""What the entry points print, configured in one place: progress bars, log lines, and the library noise left out.

A run's console is a progress bar, the lines that say what a long step does, and a summary. Three pieces:

- :class:`Progress`: tqdm to stderr that does not print its final line twice (tqdm's ``close`` repeats the last
  line, which shows as a duplicate wherever stderr is not a terminal: logs, pipes, CI).
- :class:`ProgressSafeHandler`: log records (``name: message``; ``name: warning: message`` from WARNING up) written
  to stderr with ``tqdm.write``, so a warning never lands inside a progress bar. ``conf/hydra/default.yaml`` makes it
  the console handler of every Hydra entry point (Hydra's default prints timestamps to stdout). Worker processes,
  which cannot reach the main process's bar, use :func:`worker_logging` (a line of their own).
- :func:`captured_output`: what C and C++ libraries write straight to file descriptors 1 and 2 (Patchwork++'s
  constructor, open3d's renderer), caught for the duration, one redirection at a time in the process.
- :func:`quiet`: filters exactly the messages in ``NOISE`` (library advertisements, lines about hardware that is
  absent, a deprecation inside Lightning that its users cannot act on), each matched on its own text; every other
  warning and log line shows as before. Called first by ``label.py``, ``train.py``, ``eval.py``, ``export.py`` and
  ``fastflow3d-infer``.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import sys
import tempfile
import threading
import warnings
from collections.abc import Iterator

from tqdm import tqdm

from icpflow.core.stops import raise_stop_behind

#: log lines dropped from the console (regular expressions matched at the start of the message)
NOISE = (
    r"💡 Tip: For seamless cloud logging",  # Lightning's advertisement for its LitLogger service
    r"(GPU|TPU|HPU) available: False",  # Lightning listing hardware this machine does not have
    # ONNX Runtime's int8 quantiser telling how it renamed a bias that two folded convolutions share (INFO, root logger)
    r"Created a copy of bias input ",
)
#: warnings ignored: (message regex, category); each is a library talking to its own developers
NOISE_WARNINGS = (
    # Lightning 2.6 calls torch's deprecated LeafSpec in its own pytree helper (torch >= 2.10); nothing to change here
    (r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning),
    # Lightning's guess on a resume inside an epoch; train.py's data module saves and resumes the training order
    # (fastflow3d.training.data.ShardDataModule.state_dict), which Lightning does not see
    (r"You're resuming from a checkpoint that ended before the epoch ended", UserWarning),
    # numba, at its first parallel kernel after open3d loaded its own older TBB: numba falls back to its OpenMP layer
    # (the same kernels, the same results); nothing to do for a user
    (r"The TBB threading layer requires TBB version", Warning),
)
#: loggers that Lightning gives their own console handler (they do not reach the root logger's)
LIGHTNING_LOGGERS = ("lightning.pytorch", "lightning.fabric", "lightning_fabric", "pytorch_lightning")


class NoiseFilter(logging.Filter):
    """Drops the log records whose message starts with one of ``NOISE``."""

    pattern = re.compile("|".join(f"(?:{p})" for p in NOISE))

    def filter(self, record: logging.LogRecord) -> bool:
        return not self.pattern.match(record.getMessage())


class ProgressSafeHandler(logging.Handler):
    """Log records to ``stream`` (stderr) through ``tqdm.write``, which lifts this process's progress bars out of
    the way; formatted by :class:`ConsoleFormatter` unless a formatter is set, :class:`NoiseFilter` applied."""

    def __init__(self, stream=None, level: int = logging.NOTSET) -> None:
        super().__init__(level)
        self.stream = stream
        self.setFormatter(ConsoleFormatter())
        self.addFilter(NoiseFilter())

    def emit(self, record: logging.LogRecord) -> None:
        try:
            tqdm.write(self.format(record), file=self.stream or sys.stderr)
        except Exception as error:
            raise_stop_behind(error)
            self.handleError(record)


class WorkerHandler(logging.StreamHandler):
    """A worker process's log records on stderr, each on a line of its own: on a terminal it first clears the line
    the main process's progress bar is drawn on (the bar redraws itself at its next update), so a warning never lands
    inside the bar."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)
        self.setFormatter(ConsoleFormatter())
        self.addFilter(NoiseFilter())

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        return "\r\x1b[2K" + text if getattr(self.stream, "isatty", lambda: False)() else text


def worker_logging() -> None:
    """Log records of a worker process (``label.py``'s) through :class:`WorkerHandler`, WARNING and up."""
    root = logging.getLogger()
    if not any(isinstance(handler, WorkerHandler) for handler in root.handlers):
        root.addHandler(WorkerHandler())
    quiet()


class ConsoleFormatter(logging.Formatter):
    """``<logger's last name>: message``, with ``warning:`` or ``error:`` before the message from WARNING up."""

    def format(self, record: logging.LogRecord) -> str:
        level = f"{record.levelname.lower()}: " if record.levelno >= logging.WARNING else ""
        text = f"{record.name.rsplit('.', 1)[-1]}: {level}{record.getMessage()}"
        if record.exc_info:
            text += "\n" + self.formatException(record.exc_info)
        return text


class Progress(tqdm):
    """tqdm whose ``close`` does not repeat a line already shown for the same count (see the module docstring)."""

    def __init__(self, *args, **kwargs) -> None:
        self._shown_n, self._closing = None, False
        kwargs.setdefault("file", sys.stderr)
        super().__init__(*args, **kwargs)

    def display(self, msg=None, pos=None):
        if self._closing and msg is None and self._shown_n == self.n:
            return True
        if msg is None:
            self._shown_n = self.n
        return super().display(msg, pos)

    def close(self) -> None:
        self._closing = True
        super().close()


def quiet() -> None:
    """Leave the library noise listed in ``NOISE`` and ``NOISE_WARNINGS`` out of this process's console."""
    _ignore_noise_warnings()
    for name in ("", *LIGHTNING_LOGGERS):  # filters on handlers: a logger's own filters skip its children's records
        for handler in logging.getLogger(name).handlers:
            if not any(isinstance(f, NoiseFilter) for f in handler.filters):
                handler.addFilter(NoiseFilter())


@contextlib.contextmanager
def recorded_warnings() -> Iterator[list]:
    """``warnings.catch_warnings(record=True)`` with every warning recorded each time it is raised, but those of
    ``NOISE_WARNINGS`` (a caller that prints what it records, as a stream's loop, stays as quiet as :func:`quiet`)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _ignore_noise_warnings()
        yield caught


def _ignore_noise_warnings() -> None:
    for message, category in NOISE_WARNINGS:
        warnings.filterwarnings("ignore", message=message, category=category)


#: file descriptors 1 and 2 belong to the whole process: one redirection at a time (two threads each saving and
#: restoring them unguarded lose stdout for good)
_REDIRECTION = threading.RLock()


@contextlib.contextmanager
def captured_output(fds: tuple[int, ...] = (1,)) -> Iterator[list[str]]:
    """Point the file descriptors ``fds`` (1 stdout, 2 stderr) at a temporary file for the duration; the yielded list
    holds what was written there, as lines, once the block ends. Held under one process-wide lock; where a descriptor
    cannot be duplicated (no real stdout in some embedded runners) nothing is redirected and the list stays empty."""
    lines: list[str] = []
    with _REDIRECTION, tempfile.TemporaryFile() as capture:
        sys.stdout.flush()
        sys.stderr.flush()
        try:
            saved = [os.dup(fd) for fd in fds]
        except OSError:
            yield lines
            return
        for fd in fds:
            os.dup2(capture.fileno(), fd)
        try:
            yield lines
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            for fd, copy in zip(fds, saved):
                os.dup2(copy, fd)
                os.close(copy)
            capture.seek(0)
            lines.extend(capture.read().decode(errors="replace").splitlines())
