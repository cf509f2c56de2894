"""A quiet console (icpflow.core.console): a tiny label.py and train.py run as a user runs them print a progress bar,
what long steps do and a summary, none of the library noise of issue 21; the pieces one by one."""

from __future__ import annotations

import io
import logging
import os
import re
import subprocess
import sys

import pytest
from tqdm import tqdm

from icpflow.core.console import ConsoleFormatter, NoiseFilter, Progress, WorkerHandler
from icpflow.viz.pictures import _renderer_output

from helpers.data import REPO
from helpers.training import tiny_model_overrides

#: what issue 21 found on the console, none of which may come back
NOISE = {
    "Lightning's logger advertisement": r"💡|litlogger",
    "an epoch count out of an unbounded max_epochs": r"Epoch \d+/-\d+",
    "Lightning's FLOPs of the model summary": r"FLOPs",
    "deprecation warnings": r"[Dd]eprecat|FutureWarning",
    "hardware that is absent": r"[GTH]PU available: False",
    "the open3d/Filament banner": r"FEngine|Filament|\[Open3D",
}


def _run(*args, cwd=REPO) -> str:
    env = {**os.environ, "COLUMNS": "120"}
    done = subprocess.run([sys.executable, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout + done.stderr


def _lines(output: str) -> list[str]:
    """The console's lines as a terminal shows them in turn (progress bars redraw with carriage returns)."""
    return [line.strip() for line in re.split(r"[\r\n]", output) if line.strip()]


@pytest.mark.slow
def test_tiny_label_and_train_runs_print_no_noise(tmp_path):
    shards = tmp_path / "labels"
    reader = ["dataset.reader.num_sequences=1", "dataset.reader.frames_per_sequence=2", "dataset.reader.beams=32"]
    label = _run(
        "label.py", *reader, "dataset.reader.azimuth_resolution_deg=1.0", "workers=1", f"out_dir={shards}",
        f"hydra_dir={tmp_path / 'hydra'}",
    )  # fmt: skip
    train = _run(
        "train.py", f"data.train={shards}", f"data.val={shards}", f"out_dir={tmp_path / 'run'}",
        *tiny_model_overrides(), "data.workers=0", "data.batch_size=1", "trainer.max_steps=2",
        "trainer.val_check_interval=1", "trainer.log_every_n_steps=1", "export.formats=[]",
    )  # fmt: skip
    for name, output in (("label.py", label), ("train.py", train)):
        for what, pattern in NOISE.items():
            found = [line for line in _lines(output) if re.search(pattern, line)]
            assert not found, f"{name} printed {what}: {found}"
    bars = [line for line in _lines(label) if line.startswith("labelling:") and "100%" in line]
    assert len(bars) == 1, bars  # the final bar line once
    assert "label: 1 samples labelled" in label
    assert re.search(r"training: FastFlow3D: [0-9.]+ M parameters", train)  # the model in one line
    assert re.search(r"Epoch \d+ ", train)  # the progress bar is there, without "/-2"


def test_progress_prints_its_last_line_once():
    """tqdm's close repeats the last line wherever stderr is not a terminal; Progress does not."""

    def final_lines(kind) -> list[str]:
        stream = io.StringIO()
        for _ in kind(range(3), desc="x", file=stream, mininterval=0):
            pass
        return [line for line in _lines(stream.getvalue()) if "3/3" in line]

    assert len(final_lines(tqdm)) == 2  # the defect, as tqdm has it
    assert len(final_lines(Progress)) == 1


def test_log_lines_name_their_source_and_noise_is_dropped():
    record = logging.LogRecord("fastflow3d.training", logging.WARNING, __file__, 1, "no best %s", ("checkpoint",), None)
    assert ConsoleFormatter().format(record) == "training: warning: no best checkpoint"
    info = logging.LogRecord("fastflow3d.training", logging.INFO, __file__, 1, "exported to x", None, None)
    assert ConsoleFormatter().format(info) == "training: exported to x"
    noise = NoiseFilter()
    rank_zero = "lightning.pytorch.utilities.rank_zero"
    for message, kept in (
        ("💡 Tip: For seamless cloud logging and experiment tracking, try installing [litlogger](...)", False),
        ("GPU available: False, used: False", False),
        ("GPU available: True (cuda), used: True", True),
        ("`Trainer.fit` stopped: `max_steps=4` reached.", True),
    ):
        assert noise.filter(logging.LogRecord(rank_zero, logging.INFO, __file__, 1, message, None, None)) is kept


def test_renderer_banner_is_dropped_and_anything_else_kept(capfd):
    """What open3d's renderer prints per picture is left out; any other native output still reaches stderr."""
    with _renderer_output():
        os.write(1, b"FEngine (64 bits) created at 0x55b628724bd0 (threading is enabled)\n")
        os.write(1, b"\x1b[1;33m[Open3D WARNING] GLFWWindowSystem: X11 GLFW init failed. Falling back.\x1b[0;m\n")
        os.write(2, b"[Open3D INFO] EngineInstance: Vulkan software device detected\n")
        os.write(1, b"Vulkan error: device lost\n")
    out, err = capfd.readouterr()
    assert out == "" and err == "Vulkan error: device lost\n"


def test_worker_warnings_take_a_line_of_their_own():
    """A labelling worker cannot reach the main process's bar: on a terminal its warning clears the bar's line."""

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    handler = WorkerHandler()
    for stream, start in ((Terminal(), "\r\x1b[2K"), (io.StringIO(), "")):
        handler.setStream(stream)
        record = logging.LogRecord("icpflow.core.frames", logging.WARNING, __file__, 1, "x has float16", None, None)
        handler.handle(record)
        assert stream.getvalue() == f"{start}frames: warning: x has float16\n"


def test_native_output_redirections_from_two_threads_keep_stdout(capfd):
    """Issue 31.5: file descriptor 1 is the process's; two threads each silencing it (the ground step, a picture)
    must not leave it pointing at a temporary file (one redirection at a time)."""
    import threading

    from icpflow.core.console import captured_output

    caught = []

    def silence(mark: bytes):
        for _ in range(200):
            with captured_output((1,)) as lines:
                os.write(1, mark)
            caught.append(lines)

    threads = [threading.Thread(target=silence, args=(f"{i}\n".encode(),)) for i in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    os.write(1, b"still here\n")
    out, _ = capfd.readouterr()
    assert out == "still here\n"
    assert len(caught) == 400 and all(len(lines) == 1 for lines in caught)


NUMBA_AFTER_OPEN3D = """
import numpy as np
{quiet}
from icpflow.core.open3d_loader import load_open3d
from icpflow.scans.neighbours import MAX_KNN_SHELL, build_grid, k_nearest
load_open3d()  # open3d loads its own TBB, older than numba's TBB layer wants
points = np.random.default_rng(0).uniform(-1, 1, (200, 3))
k_nearest(points, points, build_grid(points, 0.5), 0.5, 3, np.inf, MAX_KNN_SHELL, True)  # numba's first parallel kernel
"""


def test_numbas_threading_layer_warning_is_noise():
    """numba warns, at its first parallel kernel after open3d loaded an older TBB, that it takes another threading
    layer (the same results): ``quiet`` drops that line, and so does ``recorded_warnings`` (the stream's loop prints
    what it records)."""
    run = [sys.executable, "-c"]
    alone = subprocess.run([*run, NUMBA_AFTER_OPEN3D.format(quiet="")], capture_output=True, text=True, timeout=300)
    if "TBB threading layer" not in alone.stderr:
        pytest.skip("numba takes its TBB layer here, or open3d brings none: no warning to drop")
    for guard in (
        "from icpflow.core.console import quiet; quiet()",
        "from icpflow.core.console import recorded_warnings",
    ):
        code = NUMBA_AFTER_OPEN3D.format(quiet=guard)
        if "recorded" in guard:
            code = code.replace("k_nearest(points", "with recorded_warnings() as caught:\n    k_nearest(points")
            code += "print(len(caught))\n"
        done = subprocess.run([*run, code], capture_output=True, text=True, timeout=300)
        assert done.returncode == 0 and "TBB" not in done.stderr, done.stderr
        assert "recorded" not in guard or done.stdout.strip() == "0"


def test_recorded_warnings_keep_every_other_warning_each_time():
    import warnings

    from icpflow.core.console import recorded_warnings

    with recorded_warnings() as caught:
        for _ in range(2):
            warnings.warn("a scan was skipped", UserWarning, stacklevel=1)
        warnings.warn("The TBB threading layer requires TBB version 2021 update 6 or later", UserWarning, stacklevel=1)
    assert [str(warning.message) for warning in caught] == ["a scan was skipped"] * 2
