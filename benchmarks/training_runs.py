"""Training runs scored on a held-out split, for ``student_ablation`` and the frozen student studies
(``studies/steps_study``, ``studies/scaling_study``): the project's own command lines run as subprocesses in the
checkout's root, one training run scored by ``eval.py`` (skipped where its output exists, so an interrupted study
resumes), the scores read from an ``eval.py`` ``metrics.json``, and a line plot."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from benchmarks.common import ROOT
from icpflow.core.atomic import atomic_path, write_text_atomic
from icpflow.evaluation import is_complete, method_summary, read_metrics

CATEGORIES = ("dynamic_fg", "static_fg", "static_bg")


def run_python(arguments: list[str]) -> float:
    """Run ``python <arguments>`` in the repository root; seconds taken (raises on a non-zero exit)."""
    print("$ python " + " ".join(arguments), flush=True)
    tic = time.perf_counter()
    subprocess.run([sys.executable, *arguments], cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - tic


def scores(metrics_json: Path, method: str) -> dict:
    """Point-weighted EPE (m) of ``method`` per category (dynamic_fg, static_fg, static_bg) and its Threeway EPE
    (``threeway``) in an eval.py ``metrics.json``."""
    summary = method_summary(read_metrics(metrics_json), method)
    table = summary["paper"]["point_weighted"]
    return {**{c: table[c]["EPE"] for c in CATEGORIES}, "threeway": summary["threeway"]["threeway"]}


def trained_and_scored(run_dir: Path, metrics_json: Path, train: list[str], test: list[str]) -> dict:
    """Train (``train.py <train>``, ONNX export only, into ``run_dir``) unless ``run_dir/train_seconds.txt`` says it
    ran, score its export (``eval.py <test> method=[student]`` into ``metrics_json``'s folder) unless that is
    complete; the student's ``scores`` with ``seconds`` (the training's wall time)."""
    timing = run_dir / "train_seconds.txt"
    if not timing.is_file():
        seconds = run_python(
            [
                "train.py",
                *train,
                f"out_dir={run_dir}",
                "export.formats=[onnx]",
                "trainer.enable_progress_bar=false",
            ]
        )
        write_text_atomic(timing, f"{seconds:.1f}\n")
    return {**evaluated(metrics_json, test, "student", run_dir / "export"), "seconds": float(timing.read_text())}


def evaluated(metrics_json: Path, overrides: list[str], method: str, checkpoint: Path | None = None) -> dict:
    """``scores`` of ``method`` by ``eval.py <overrides>`` (with ``checkpoint=`` where given) into
    ``metrics_json``'s folder, run only where that is not complete."""
    if not is_complete(metrics_json):
        model = [f"checkpoint={checkpoint}"] if checkpoint is not None else []
        run_python(["eval.py", *overrides, f"method=[{method}]", *model, f"out_dir={metrics_json.parent}"])
    return scores(metrics_json, method)


def save_line_plot(path: Path, title: str, xlabel: str, curves: list[tuple], references: list[tuple]) -> None:
    """A PNG (written atomically) of ``curves`` ``(xs, ys, style, label)`` on a log2 x axis with horizontal
    ``references`` ``(y, colour, linestyle, label)`` (the teacher, ego-only); y: EPE on the test split."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(6, 4))
    for xs, ys, style, label in curves:
        axis.plot(xs, ys, style, label=label)
    for y, colour, linestyle, label in references:
        axis.axhline(y, color=colour, linestyle=linestyle, label=label)
    axis.set_xscale("log", base=2)
    axis.set_xlabel(xlabel)
    axis.set_ylabel("EPE (m), test split")
    axis.set_title(title)
    axis.legend(fontsize=8)
    figure.tight_layout()
    with atomic_path(path) as tmp:
        figure.savefig(tmp, dpi=120, format="png")
    plt.close(figure)
    print(f"wrote {path}")
