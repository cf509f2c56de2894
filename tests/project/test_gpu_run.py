"""The GPU run of issue 34.4 (``python -m benchmarks.gpu_run``), smoke-tested on the CPU with tiny sizes: every step
runs (labelling, both recipes' training with their export, scoring beside the teacher and ego-only, the latency
tables with eager and eager bf16, the stream's, the teacher's two ICP backends) and the report holds each table."""

import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import gpu_run

from helpers.data import REPO, shared
from helpers.labelling import TESTS_ENV

STEPS = ("labels_train", "labels_val", "train_paper", "train_small", "eval_paper", "eval_small", "teacher")


def _smoke(out: Path) -> subprocess.CompletedProcess:
    """``python -m benchmarks.gpu_run --smoke --out <out>`` in the checkout's root."""
    return subprocess.run(
        [sys.executable, "-m", "benchmarks.gpu_run", "--smoke", "--out", str(out)],
        cwd=REPO,
        env=TESTS_ENV,
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    out = tmp_path_factory.mktemp("gpu_run")
    return out, _smoke(out)


@pytest.mark.slow  # about a minute: every step's subprocess imports torch
def test_every_step_of_the_gpu_run_runs_on_the_cpu(smoke):
    out, result = smoke
    assert result.returncode == 0, result.stdout[-3000:]
    report = (out / "report.md").read_text()
    for step in STEPS:
        assert f"| {step} |" in report, step
    for name in ("paper", "small"):
        assert (out / f"train_{name}" / "export" / "fastflow3d.onnx").is_file()
        assert f"| {name} | 2 |" in report  # the steps each student reached
    assert "Created a copy of bias input" not in (out / "logs" / "train_small.log").read_text()  # its int8 export
    for method in ("ego", "icpflow", "student (paper)", "student (small)"):
        assert f"| {method} |" in report, method
    for backend in ("eager", "eager-bf16"):  # both models
        assert report.count(f"| given | {backend} |") == 2, backend
    assert "| cpu | cpu (numba" in report and "| torch | cpu" in report  # the teacher's two backends
    assert "| stream | points | regime | engine |" in report  # the stream's table (issue 33.7), rows with the data
    if shared("kitti_hdl64_scans").is_dir():
        assert report.count("| kitti | 124668 | streamed | eager |") == 1
        for refined in ("no", "yes"):  # the stream as a user runs it (issue 44.6; on a GPU: its pt2 network)
            assert f"| kitti | {gpu_run.SMOKE_CLI_FRAMES} | onnxruntime | {refined} |" in report, refined


def test_steps_picks_steps_and_refuses_an_unknown_one(tmp_path):
    command = [sys.executable, "-m", "benchmarks.gpu_run", "--smoke", "--out", str(tmp_path)]
    result = subprocess.run([*command, "--steps", "teacher,nope"], cwd=REPO, env=TESTS_ENV, capture_output=True)
    assert result.returncode == 2 and b"--steps: unknown nope; steps: labels_train," in result.stderr
    assert not (tmp_path / "logs").exists()  # nothing ran


@pytest.mark.slow
def test_a_second_run_skips_what_is_done(smoke):
    out, _ = smoke
    again = _smoke(out)
    assert again.returncode == 0, again.stdout[-3000:]
    for step in (*STEPS, "latency_paper", "latency_small", "latency_stream", "latency_cli"):
        assert f"gpu_run: {step}: done before" in again.stdout, step


def test_a_step_is_done_only_once_its_command_exited_zero(tmp_path):
    """A killed step (a partial metrics.json on the device, 2026-11-27) runs again on the next call; a finished one
    is skipped."""
    output = tmp_path / "metrics.json"
    write = f"open({str(output)!r}, 'a').write('x')"
    seconds = {}
    assert not gpu_run.Step(tmp_path, "eval", ["-c", f"{write}; raise SystemExit(3)"]).run(seconds)
    assert output.read_text() == "x" and not (tmp_path / "logs" / "eval.done").exists()
    assert gpu_run.Step(tmp_path, "eval", ["-c", write]).run(seconds) and output.read_text() == "xx"
    assert gpu_run.Step(tmp_path, "eval", ["-c", write]).run(seconds) and output.read_text() == "xx"  # skipped


def test_the_cli_benchs_stream_length_is_checked(tmp_path):
    # --frames (the smoke's short CLI stream): refused in one line where no frame would be timed, and outside --mode cli
    command = [sys.executable, "-m", "benchmarks.bench_student_latency", "--export", str(tmp_path)]
    short = subprocess.run([*command, "--mode", "cli", "--frames", "6"], cwd=REPO, capture_output=True, text=True)
    assert short.returncode == 2 and "--frames must be at least 7 (one timed frame), got 6" in short.stderr
    other = subprocess.run([*command, "--mode", "refine", "--frames", "8"], cwd=REPO, capture_output=True, text=True)
    assert other.returncode == 2 and "--frames is not an option of --mode refine" in other.stderr
