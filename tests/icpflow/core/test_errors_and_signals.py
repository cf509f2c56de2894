"""icpflow.core.errors_and_signals, the one way every entry point stops and reports (issue 32): a signal routed by
``on_signals`` (a forked child ignores it; an inherited ignored SIGINT stays ignored; the previous handlers come back),
``Stop``'s line and exit status, ``exit_status`` (the report of ``reported`` as a return value), ``one_line``,
fastflow3d-infer stopped; and a ``Stop`` raised inside label.py's and eval.py's bodies: 143 / 130 with their own lines,
in this process. The scripts under real signals: test_faults.py (label.py, SIGTERM), test_label.py (label.py, Ctrl-C),
test_faults_evaluation.py (eval.py, both), test_faults_training.py (train.py, both)."""

import errno
import os
import signal
import sys
import time

import pytest
from hydra import compose, initialize_config_dir

from icpflow.core.errors_and_signals import (
    STOP_SIGNALS,
    Stop,
    exit_status,
    on_signals,
    one_line,
    signals_held,
    stop_behind,
    stop_on_signals,
    stop_signum,
)
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.evaluation import run_eval
from icpflow.evaluation.baselines import ego_only_flow

from helpers.labelling import REPO, label_cfg

CASES = [(signal.SIGINT, 130, "interrupted (SIGINT)"), (signal.SIGTERM, 143, "terminated (SIGTERM)")]


@pytest.fixture
def handlers():
    """This process's handlers of the stop signals, put back after the test; Ctrl-C at Python's default even where
    pytest runs as a background job (SIGINT ignored)."""
    before = {signum: signal.getsignal(signum) for signum in STOP_SIGNALS}
    signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    for signum, handler in before.items():
        signal.signal(signum, handler)


def _signal_self(signum: int) -> None:
    """Send ``signum`` to this process and give its Python handler the moment to run."""
    os.kill(os.getpid(), signum)
    for _ in range(100):
        time.sleep(0.01)


@pytest.mark.parametrize(("signum", "status", "words"), CASES)
def test_a_signal_in_the_block_is_a_stop_and_the_handlers_come_back(handlers, signum, status, words):
    before = {s: signal.getsignal(s) for s in STOP_SIGNALS}
    with pytest.raises(Stop) as stopped, stop_on_signals():
        _signal_self(signum)
    assert (stopped.value.status, str(stopped.value), stop_signum(stopped.value)) == (status, words, signum)
    assert {s: signal.getsignal(s) for s in STOP_SIGNALS} == before
    assert stop_signum(KeyboardInterrupt()) == signal.SIGINT  # Ctrl-C where no handler of ours ran


def test_a_handler_may_note_the_signal_instead(handlers):
    """LastCheckpoint's way: the first signal is noted, the training step goes on."""
    noted = []
    restore = on_signals(noted.append)
    try:
        _signal_self(signal.SIGTERM)
    finally:
        restore()
    assert noted == [signal.SIGTERM]
    restore()  # twice: nothing more to put back


def test_a_forked_child_ignores_the_stop_signals(handlers):
    """A DataLoader or library worker forked from the run: its owner ends it, Ctrl-C to the group does not."""
    with stop_on_signals():
        pid = os.fork()
        if pid == 0:  # the child: survives both signals
            code = 1
            try:
                _signal_self(signal.SIGINT)
                _signal_self(signal.SIGTERM)
                code = 0
            finally:
                os._exit(code)
        _, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0


def test_an_ignored_sigint_stays_ignored(handlers):
    """A background job of a shell script starts with SIGINT ignored: Python leaves it so, and so does the run."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with stop_on_signals():
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        _signal_self(signal.SIGINT)
        with pytest.raises(Stop):
            _signal_self(signal.SIGTERM)
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN


def test_exit_status_is_the_report_of_every_entry_point(monkeypatch, capsys):
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)

    def raising(error):
        def body():
            raise error

        return body

    assert exit_status("prog", lambda: None) == 0 and exit_status("prog", lambda: 1) == 1
    cases = [
        (raising(ValueError("bad\n   value")), (ValueError,), 2, "prog: bad value"),
        (
            raising(FileNotFoundError(errno.ENOENT, "No such file", "x.npy")),
            (),
            2,
            "prog: x.npy: No such file; check the path",
        ),
        (raising(Stop(signal.SIGTERM, "terminated (SIGTERM); kept")), (), 143, "prog: terminated (SIGTERM); kept"),
        (raising(KeyboardInterrupt()), (), 130, "prog: interrupted (SIGINT)"),
        (
            raising(TypeError("oops")),
            (),
            2,
            "prog: unexpected TypeError: oops (set HYDRA_FULL_ERROR=1 for the traceback)",
        ),
    ]
    for body, expected, status, line in cases:
        assert exit_status("prog", body, *expected) == status
        assert capsys.readouterr().err == line + "\n"


@pytest.mark.parametrize(("signum", "status", "words"), CASES)
def test_fastflow3d_infer_stops_with_one_line_as_every_entry_point(
    handlers, monkeypatch, capsys, signum, status, words
):
    from fastflow3d.inference import cli

    monkeypatch.setattr(cli, "infer", lambda args: _signal_self(signum))
    assert cli.main(["model", "scan0.npy", "scan1.npy"]) == status
    assert capsys.readouterr().err == f"infer: {words}\n"


def test_one_line():
    assert one_line("a\n  b\tc ") == "a b c" and one_line(ValueError("x\ny")) == "x y"


# ----------------------------------------------------------------------------- Stop inside label.py and eval.py


class SignalOnRead(SyntheticDataset):
    """The small synthetic world whose first pair, when read, sends ``signum`` to this process."""

    def __init__(self, signum, **kwargs):
        super().__init__(**kwargs)
        self.signum = signum

    def pair(self, index, horizon=1):
        _signal_self(self.signum)
        return super().pair(index, horizon)


@pytest.mark.parametrize(
    ("signum", "status", "what"), [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated (SIGTERM)")]
)
def test_a_signal_during_labelling_keeps_the_shards_and_exits_128_plus_it(
    handlers, tmp_path, monkeypatch, capsys, signum, status, what
):
    from icpflow.labelling import cli

    monkeypatch.setattr(cli, "ensure_compiled", lambda prog: None)  # the teacher never runs here
    cfg = label_cfg(tmp_path, f"dataset.reader._target_={__name__}.SignalOnRead", f"+dataset.reader.signum={signum}")
    before = {s: signal.getsignal(s) for s in STOP_SIGNALS}
    assert cli.label(cfg, progress=False) == status
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"label: {what}; complete shards are kept in {tmp_path}, rerun the same command to resume"
    )
    assert {s: signal.getsignal(s) for s in STOP_SIGNALS} == before  # the handlers came back
    wrapped = SystemError("a numba kernel returned a result with an exception set")
    wrapped.__cause__ = Stop(signum)
    assert stop_behind(wrapped) is wrapped.__cause__  # a stop inside a kernel stops the run


@pytest.mark.parametrize(
    ("signum", "status", "what"),
    [(signal.SIGINT, 130, "interrupted (Ctrl-C)"), (signal.SIGTERM, 143, "terminated (SIGTERM)")],
)
def test_a_signal_during_evaluation_keeps_a_partial_result_and_exits_128_plus_it(
    handlers, tmp_path, capsys, signum, status, what
):
    def signalling(pair, index):
        _signal_self(signum)
        return ego_only_flow(pair)

    small = ["dataset.reader.num_sequences=1", "dataset.reader.frames_per_sequence=3", "dataset.reader.beams=32"]
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("eval", [*small, "method=[signalling]", "bev=0", f"out_dir={tmp_path}"])
    assert run_eval(cfg, progress=False, extra_methods={"signalling": lambda cfg: signalling}) == status
    assert capsys.readouterr().err.splitlines()[-1] == (
        f'eval: {what}; the 0 pairs scored are kept in {tmp_path / "metrics.json"} ("complete": false); '
        "rerun the same command for all pairs"
    )


def test_signals_are_held_around_a_threaded_library_call_and_delivered_after_it(handlers):
    """A signal that reaches a library call running its own threads (cKDTree.query with workers, whose own join is
    where it lands) is delivered when the call is over, to the handler installed before: raising inside the call
    unwound it while its threads still wrote into its memory (label.py segfaulted after Ctrl-C, about 1 run in 10
    under load)."""
    import threading

    done = threading.Event()

    def work():
        time.sleep(0.3)
        done.set()

    with pytest.raises(Stop) as stopped, stop_on_signals():
        with signals_held():
            worker = threading.Thread(target=work, daemon=True)
            worker.start()
            threading.Timer(0.05, os.kill, (os.getpid(), signal.SIGINT)).start()
            worker.join()  # not interrupted
            assert done.is_set()
        pytest.fail("the held signal was not delivered after the call")
    assert stopped.value.signum == signal.SIGINT
    with pytest.raises(KeyboardInterrupt):  # no stop handler: Python's own, after the call as well
        with signals_held():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    with signals_held():  # nothing arrived: nothing delivered
        pass


def test_without_signal_masks_the_block_runs_as_it_is(monkeypatch):
    """Windows has no ``signal.pthread_sigmask``: the one way to hold signals (evaluation's sums, scipy's threaded
    queries) needs none, a signal inside the block still waits for its end."""
    monkeypatch.delattr(signal, "pthread_sigmask")
    ran = []
    with pytest.raises(KeyboardInterrupt):
        with signals_held():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)
            ran.append(True)
    assert ran == [True]


def test_a_stop_that_a_kernel_wraps_is_the_stop(capsys):
    """A signal whose handler runs while a compiled kernel returns surfaces as ``SystemError: CPUDispatcher(...)
    returned a result with an exception set`` caused by the Stop: it is read as the Stop it wraps (exit 128 + N and
    its line), any other SystemError stays one."""
    from icpflow.core.errors_and_signals import exit_status, stopped_by

    def wrapped(stop: BaseException):
        try:
            raise stop
        except BaseException as cause:
            raise SystemError("CPUDispatcher(<function nearest>) returned a result with an exception set") from cause

    def body():
        wrapped(Stop(signal.SIGTERM))

    assert exit_status("infer", body) == 143
    assert capsys.readouterr().err == "infer: terminated (SIGTERM)\n"
    with pytest.raises(SystemError) as raised:
        wrapped(KeyboardInterrupt())
    assert isinstance(stopped_by(raised.value), KeyboardInterrupt)
    with pytest.raises(SystemError, match="other"):
        stopped_by(SystemError("other"))


#: a process that starts as an entry point does, through ``launched``, and whose command imports numba for the first
#: time inside its report; the stop arrives while numba's compiled dispatcher imports its sibling module (Python's
#: import machinery runs a finder there, as it runs a signal's handler): numba prints it and raises an ImportError
INTERRUPTED_IMPORT = """
import signal, sys
from icpflow.core.errors_and_signals import Stop, reported
from icpflow.core.launch import launched

class Interrupting:
    def find_spec(self, name, path=None, target=None):
        if name == "numba._devicearray":
            raise KeyboardInterrupt if sys.argv[1] == "SIGINT" else Stop(signal.SIGTERM)

def load():
    def main():
        with reported("label"):
            import numba
    return main

sys.meta_path.insert(0, Interrupting())
launched("label", load)
"""


@pytest.mark.parametrize(("name", "status", "words"), [("SIGINT", 130, "interrupted"), ("SIGTERM", 143, "terminated")])
def test_a_stop_inside_a_compiled_modules_import_is_the_stop(name, status, words):
    """A Ctrl-C while numba's compiled modules import (the first moment a command needs the teacher, a second into
    ``label.py``) is printed by numba and replaced by ``ImportError: numba._devicearray failed to import``: it ends
    as the stop it replaced, one line and 128 + the signal, nothing printed before it."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", INTERRUPTED_IMPORT, name], capture_output=True, text=True, timeout=120)
    assert (done.returncode, done.stderr) == (status, f"label: {words} ({name})\n")


def test_an_import_error_is_a_stop_only_over_a_printed_stop(monkeypatch):
    """The ImportError that a compiled module raises in place of a stop it printed (``sys.last_value``) is that stop;
    one over any other printed error, or none, stays an error."""
    from icpflow.core.errors_and_signals import stopped_by

    error = ImportError("numba._devicearray failed to import")
    monkeypatch.delattr(sys, "last_value", raising=False)
    assert stop_behind(error) is None
    monkeypatch.setattr(sys, "last_value", ValueError("printed"), raising=False)
    with pytest.raises(ImportError):
        stopped_by(error)
    for stop in (KeyboardInterrupt(), Stop(signal.SIGTERM)):
        monkeypatch.setattr(sys, "last_value", stop, raising=False)
        assert stopped_by(error) is stop
    # a Ctrl-C that an interactive session printed long ago is no stop behind an ImportError of its own: a missing
    # package, or one raised over another error
    monkeypatch.setattr(sys, "last_value", KeyboardInterrupt(), raising=False)
    assert stop_behind(ImportError("onnxruntime is not installed")) is None
    try:
        raise ValueError("inner")
    except ValueError as inner:
        over = ImportError("x failed to import")
        over.__cause__ = inner
    assert stop_behind(over) is None


def _raise(error: BaseException):
    raise error


def _converted(*args, **kwargs):
    """What numpy's ``import_array`` raises in a compiled module's import after it printed the stop."""
    _raise(ImportError("numpy.core.multiarray failed to import"))


@pytest.mark.parametrize("stop", [KeyboardInterrupt(), Stop(signal.SIGTERM)], ids=["SIGINT", "SIGTERM"])
def test_a_stop_turned_into_an_import_error_passes_every_fallback(monkeypatch, stop):
    """The cousins of the CI failure: a stop that arrives while an import inside a broad handler's ``try`` runs (a
    reader's module, a config target, numba's cache index, an optional package) is printed by the compiled module and
    replaced by an ImportError; each handler raises the stop, none takes it for an unimportable reader (a run that went
    on to the end, exit 0: one probe of 80), a bad target or a cold cache. ``tests/project/test_architecture.py``
    checks that every broad handler of the packages does so."""
    from omegaconf import OmegaConf

    from icpflow.core import open3d_loader, settings
    from icpflow.datasets.from_config import raise_max_horizon
    from icpflow.teacher import warmup

    monkeypatch.setattr(sys, "last_value", stop, raising=False)
    monkeypatch.setattr("hydra.utils.get_class", _converted)
    monkeypatch.setattr("hydra.utils.get_object", _converted)
    cfg = OmegaConf.create({"dataset": {"reader": {"_target_": "some.Reader"}}})

    class Dispatcher:
        @property
        def _cache(self):
            _converted()

    class Converting:  # a compiled module's import that printed the stop: the finder Python's import runs
        def find_spec(self, name, path=None, target=None):
            if name == "libusb_package":
                _converted()

    monkeypatch.delitem(sys.modules, "libusb_package", raising=False)
    monkeypatch.setattr(sys, "meta_path", [Converting(), *sys.meta_path])
    monkeypatch.setattr(open3d_loader.ctypes, "CDLL", lambda *args, **kwargs: _raise(OSError("no libusb")))
    for call in (
        lambda: raise_max_horizon(cfg, 2),
        lambda: settings.check_target_arguments(OmegaConf.create({"_target_": "some.Model", "x": 1}), "model"),
        lambda: warmup._cached(Dispatcher()),
        open3d_loader.provide_libusb,
    ):
        with pytest.raises(type(stop)) as raised:
            call()
        assert raised.value is stop


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_inside_a_compiled_call_stops_the_evaluation(signum):
    """A stop that a kernel wraps in a SystemError while a method predicts stops ``evaluate`` (the CLI keeps the pairs
    scored, above); it is not a bad sample recorded and skipped."""
    from icpflow.evaluation import MetricOptions, evaluate

    dataset = SyntheticDataset(
        split="val", num_sequences=1, frames_per_sequence=3, beams=32, azimuth_resolution_deg=1.0
    )

    def kernel(pair, index):
        try:
            raise Stop(signum)
        except Stop as stop:
            raise SystemError("CPUDispatcher(<function nearest>) returned a result with an exception set") from stop

    with pytest.raises(Stop) as stopped:
        evaluate(dataset, {1: {"kernel": kernel}}, MetricOptions())
    assert stopped.value.signum == signum


#: a command started as an entry point is (``launched``) in which a library swallows a stop: ``hydra`` as Hydra's
#: ``get_mode`` does before the command's own work (``except Exception`` over the error omegaconf raised over the
#: stop), ``cython`` as numpy's Cython modules do while they import (their ABC registrations ignore every error: the
#: signal lands in ``abc.register``, as one of 150 probes of ``label.py`` showed); ``omegaconf`` as omegaconf's
#: config creation does where Hydra composes the run's config: an error of its own over the stop escapes;
#: ``weakref`` as Python does with a stop raised in a callback it cannot raise from (importlib's module locks')
SWALLOWED = """
import os, signal, sys, weakref
from icpflow.core.errors_and_signals import reported, stop_on_signals
from icpflow.core.launch import launched

where, signum = sys.argv[1], getattr(signal, sys.argv[2])


class Thing:
    pass


def in_abc_register(frame, event, arg):
    if event == "call" and frame.f_code.co_name == "register" and "numpy.random._generator" in sys.modules:
        sys.settrace(None)
        signal.raise_signal(signum)


def load():
    def main():
        with reported("label"):
            if where == "hydra":
                try:
                    try:
                        signal.raise_signal(signum)
                    except BaseException as stop:
                        raise ValueError("omegaconf's error") from stop
                except Exception:
                    pass
            if where == "weakref":  # a callback Python cannot raise from: the stop is "ignored", printed
                thing = Thing()
                ref = weakref.ref(thing, lambda gone: signal.raise_signal(signum))
                del thing
            if where == "omegaconf":  # its error over the stop escapes Hydra's compose (its context: the stop)
                try:
                    signal.raise_signal(signum)
                except BaseException:
                    raise AttributeError("'NoneType' object has no attribute '_invalidate_flags_cache'")
            with stop_on_signals():
                if where == "cython":
                    assert "numpy.random" not in sys.modules
                    sys.settrace(in_abc_register)
                    import numpy.random
                    assert "numpy.random._generator" in sys.modules  # the import went on over the stop
                print("the long work", file=sys.stderr)
        return 0
    return main

launched("label", load)
"""


@pytest.mark.parametrize("name", ["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("where", ["hydra", "weakref", "omegaconf", "cython"])
def test_a_stop_a_library_swallowed_still_stops_the_command(where, name):
    """A stop that a library swallows is no lost Ctrl-C (one probe of 80 of ``label.py`` ran to the end and exited 0):
    one swallowed before the command's work (Hydra's) stops it where the work starts (``stop_on_signals``), nothing
    done; an error raised over it is the stop; one swallowed inside it (a Cython module's import) ends the command
    as stopped, 128 + the signal, in its line."""
    import subprocess

    done = subprocess.run(
        [sys.executable, "-c", SWALLOWED, where, name], capture_output=True, text=True, timeout=120, cwd=REPO
    )
    words = "interrupted" if name == "SIGINT" else "terminated"
    work = "the long work\n" if where == "cython" else ""
    assert (done.returncode, done.stderr) == (128 + getattr(signal, name), f"{work}label: {words} ({name})\n")


#: each entry point as its console script or checkout script starts it (``icpflow.core.launch``)
STARTS = {
    "label": [str(REPO / "label.py"), "dataset.reader.num_sequences=1"],
    "train": [str(REPO / "train.py"), "trainer.max_steps=1"],
    "eval": [str(REPO / "eval.py"), "limit=1"],
    "export": [str(REPO / "export.py"), "checkpoint=missing.ckpt"],
    "infer": ["-c", "import sys; from fastflow3d.inference.launch import infer; sys.exit(infer())", "missing.npy"],
}
#: the moments each start is signalled at (s): train's start is the longest, SIGTERM takes the path SIGINT takes
DELAYS = {signal.SIGINT: (0.6, 1.6), signal.SIGTERM: (1.0,)}
#: where the command had started and refused its missing input already, its refusal is its answer
REFUSES = {"infer", "export"}


def _ctrl_c_at_default():
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
@pytest.mark.parametrize("prog", sorted(STARTS))
def test_a_signal_while_an_entry_point_starts_is_one_line_and_128_plus_it(prog, signum, tmp_path):
    """A Ctrl-C or a SIGTERM while the command still imports its libraries (torch, numba, Hydra: seconds) ends as at
    any other moment: one line naming the program and the signal, exit 128 + the signal, no traceback and no end by
    the signal itself; sent at several moments of the start."""
    import subprocess
    import sys

    words = {signal.SIGINT: "interrupted", signal.SIGTERM: "terminated"}[signum]
    for delay in DELAYS[signum] if prog != "train" else (1.0,):
        process = subprocess.Popen(
            [sys.executable, *STARTS[prog]],
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            preexec_fn=_ctrl_c_at_default,  # where pytest runs as a background job, its children ignore SIGINT
        )
        time.sleep(delay)
        process.send_signal(signum)
        _, err = process.communicate(timeout=300)
        if process.returncode == 2 and prog in REFUSES:
            continue
        assert process.returncode == 128 + signum, (prog, delay, process.returncode, err[-600:])
        assert "Traceback" not in err, (prog, delay, err[-2000:])
        assert err.strip().splitlines()[-1].startswith(f"{prog}: {words}"), (prog, delay, err[-600:])


def test_a_signal_outside_the_commands_own_report_is_its_line_and_128_plus_it(handlers, capsys):
    """A Ctrl-C that lands in ``main`` before its report begins (while it parses its options: 1 try in 10 of
    fastflow3d-infer's start) or after it ended is the line ``<prog>: interrupted (SIGINT)`` and 130, not Python's
    traceback; a SIGTERM there is ``terminated (SIGTERM)`` and 143, not an end by the signal; one while the command
    loads waits for the load and says nothing was done; a main that returns keeps its status, and a signal
    after it, while the process exits, is ignored."""
    from icpflow.core.launch import launched

    def main(*args):
        raise KeyboardInterrupt

    def terminated(*args):
        _signal_self(signal.SIGTERM)
        return 0

    def loaded_under_sigterm():
        _signal_self(signal.SIGTERM)
        return lambda *args: 0

    for load, status, line in [
        (lambda: main, 130, "infer: interrupted (SIGINT)"),
        (lambda: terminated, 143, "infer: terminated (SIGTERM)"),
        (loaded_under_sigterm, 143, "infer: terminated (SIGTERM) while starting; nothing was done"),
    ]:
        with pytest.raises(SystemExit) as stopped:
            launched("infer", load, ["a.npy"], exits=False)
        assert stopped.value.code == status
        assert capsys.readouterr().err == line + "\n"
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the handlers are back
    assert launched("infer", lambda: lambda *args: 2, ["a.npy"], exits=False) == 2
    assert launched("infer", lambda: lambda *args: 2, ["a.npy"]) == 2  # a process that ends now: its status stands
    assert {signal.getsignal(signum) for signum in STOP_SIGNALS} == {signal.SIG_IGN}


def test_a_bare_tilde_in_an_override_says_how_to_quote_it():
    """Hydra's grammar refuses ``out_dir=~/lab`` (a ``~`` the shell left, or one quoted for the shell only); the line
    says how to write that override so that Hydra takes it (and the entry points expand it: ``home``)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from icpflow.core.errors_and_signals import error_line

    with pytest.raises(Exception) as raised:
        OverridesParser.create().parse_overrides(["out_dir=~/lab"])
    line = error_line(raised.value)
    assert "\n" not in line and """(a path with ~ is quoted for Hydra: "out_dir='~/lab'")""" in line, line
    assert OverridesParser.create().parse_overrides(["out_dir='~/lab'"])[0].value() == "~/lab"
