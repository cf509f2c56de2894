"""One command for a GPU machine: label, train the two students for a fixed time each, score them beside the teacher
and ego-only, and time the network and the teacher's ICP on the GPU (issue 34.4).

    python3 -m benchmarks.gpu_run [--out outputs/gpu_run] [--minutes 3] [--workers 16] [--train-sequences 256]
        [--test-pairs 64] [--data ../shared/data]
    python3 -m benchmarks.gpu_run --smoke --out <dir>    # tiny sizes on the CPU (tests/project/test_gpu_run.py)

Run from the checkout's root: ``-m`` puts it first on Python's path, so neither the project nor ``benchmarks`` need
be installed (the device machine's run: ``run(command="python3 -m benchmarks.gpu_run ...", carry=[".wheels"])``).

The steps are the project's own command lines, each a subprocess with its log in ``<out>/logs/<step>.log``; a step
that finished (exit 0: ``<out>/logs/<step>.done``) is skipped when the command runs again, and an interrupted one runs
again (labelling and training resume where they stopped; a partial score file is written anew):

1. ``labels``: ``label.py`` on ``--train-sequences`` synthetic sequences of 3 frames (2 pairs each) and the val split,
   with ``--workers`` processes;
2. ``train_paper`` and ``train_small``: ``train.py experiment=paper`` (FastFlow3D 512 x 512, 6.8 M parameters) and
   ``experiment=synthetic_cpu`` (the CPU recipes' small model), each ``--minutes`` of training
   (``trainer.max_time``) on the GPU in bf16-mixed, exported to ONNX;
3. ``eval``: ``eval.py`` on ``--test-pairs`` synthetic test pairs: ego-only, the teacher and the paper student; the
   small student on the same pairs;
4. ``latency_paper`` and ``latency_small``: ``benchmarks.bench_student_latency --device cuda`` (its pair mode)
   with backends ``eager``, ``eager-bf16`` and ``onnx`` (ONNX Runtime's CUDA provider, where ``onnxruntime-gpu`` is
   installed), median of 100 calls after 10, on the shipped KITTI and AV2 scans, poses given; ``latency_stream``
   (issue 33.7): ``benchmarks.bench_student_latency --mode stream --device cuda``, the small model's network on the
   GPU with the same backends, the shipped scans played as streams, regimes ``streamed`` (nothing given) and
   ``given``, 102 frames each after the first two of each pass, the process held to 2 CPU cores (ground and
   odometry as on the 2-core laptop); ``latency_cli`` (issue 44.6): the stream as a user runs it
   (``bench_student_latency --mode cli``: ``fastflow3d-infer EXPORT DIR --out OUT [--refine]``, whole runs) with
   the export's torch.export network on the GPU (``--backend pt2 --device cuda``) and every other step on 2 cores,
   plain and refined, on the KITTI, AV2 and synthetic streams; the export is ``--stream-export`` (a trained
   student's, carried) or ``train_small``'s own;
5. ``teacher``: ``benchmarks.teacher_backends --av2 <data>/av2``: ``icp.backend=torch`` (CUDA) against the CPU
   backend on the shipped Argoverse 2 pair: time of each and the largest flow difference (synthetic pairs where the
   AV2 sample is absent).

``--steps a,b`` runs only the named steps (e.g. ``latency_stream,latency_small`` first when device time is short).
``<out>/report.md`` then holds every table: the steps' wall times, the students' steps reached, the scores (dynamic
foreground, Threeway and static foreground EPE, each student's ratio to the teacher and to ego-only), the latency
and the teacher tables. Sized for under 10 minutes of a 16-core H100/H200 machine with ``--minutes 3``.

The device machine reaches no package registry. Its image (2026-11) holds torch (CUDA), lightning, onnxruntime (CPU),
pandas, pyarrow, scikit-learn, tensorboard, tqdm and pyyaml; what it lacked on 2026-11-27, as cp312 wheels in a
git-ignored ``.wheels/`` folder named in the run's ``carry`` (64 MiB in all, 10 MB of these): hydra-core omegaconf
antlr4-python3-runtime (built with ``pip wheel``: it has no wheel on PyPI) hdbscan kiss-icp pypatchworkpp pebble and
kiss-icp's pydantic pydantic-core pydantic-settings python-dotenv annotated-types typing-inspection typing-extensions
natsort pyquaternion (``pip download --no-deps --only-binary=:all: --python-version 3.12 ...``); this script
installs ``.wheels/*.whl`` first where the folder exists (``--no-index --no-deps``). Two do not fit the carry as
wheels: ``open3d-cpu`` (99 MB; the stream's odometry needs it: ``bash benchmarks/pack_open3d.sh`` writes
``.wheels/open3d.tar.xz``, 41 MB, which this script unpacks and puts first on the steps' ``PYTHONPATH`` and
``LD_LIBRARY_PATH``) and ``onnxruntime-gpu`` (over 200 MB: without its CUDA provider the GPU latency steps have no
``onnx`` rows). The ``teacher`` step on the AV2 sample also
needs the ``av2`` package.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from icpflow.core.atomic import write_text_atomic

ROOT = Path(__file__).resolve().parents[1]
#: the tiny network of --smoke, the tests' (conf/model/fastflow3d_tiny.yaml): as bench_student_latency's --model
SMOKE_LATENCY_MODEL = ["--model", "fastflow3d_tiny"]
#: scans of the smoke's CLI stream (bench_student_latency --frames): two timed frames, a third of the full stream's time
SMOKE_CLI_FRAMES = 8


def smoke_model() -> list[str]:
    """train.py's overrides that make its network the tiny one (every key of conf/model/fastflow3d_tiny.yaml, so an
    experiment's own model settings are replaced). PyYAML is read lazily: lightning brings it, the wheels are not
    installed yet when this script starts."""
    import yaml

    tiny = yaml.safe_load((ROOT / "conf" / "model" / "fastflow3d_tiny.yaml").read_text())
    return [f"model.{key}={json.dumps(value)}" for key, value in tiny.items() if key != "defaults"]


class Step:
    """One command of the run, logged to ``<out>/logs/<name>.log``, skipped where ``done`` exists."""

    def __init__(self, out: Path, name: str, arguments: list[str], cpus: int | None = None):
        self.out, self.name, self.arguments, self.cpus = out, name, arguments, cpus
        #: written once the command exits 0: an output alone (a killed eval.py's partial metrics.json) is no proof
        self.done = out / "logs" / f"{name}.done"

    def run(self, seconds: dict) -> bool:
        """Run it unless done; its wall time goes to ``seconds[name]``; False (said on stderr) when it failed."""
        if self.done.exists():
            print(f"gpu_run: {self.name}: done before ({self.done}), skipped", flush=True)
            return True
        log = self.out / "logs" / f"{self.name}.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        print(f"gpu_run: {self.name}: python {' '.join(self.arguments)}", flush=True)
        tic = time.perf_counter()
        usable = sorted(os.sched_getaffinity(0))
        held = set(usable[: self.cpus]) if self.cpus else None
        with open(log, "w") as handle:
            result = subprocess.run(
                [sys.executable, *self.arguments],
                cwd=ROOT,
                stdout=handle,
                stderr=subprocess.STDOUT,
                preexec_fn=(lambda: os.sched_setaffinity(0, held)) if held else None,
            )
        seconds[self.name] = time.perf_counter() - tic
        if result.returncode != 0:
            tail = log.read_text().strip().splitlines()[-3:]
            print(f"gpu_run: {self.name} failed (exit {result.returncode}, {log}): {' | '.join(tail)}", flush=True)
            return False
        self.done.touch()
        print(f"gpu_run: {self.name}: {seconds[self.name]:.0f} s", flush=True)
        return True


def install_wheels() -> None:
    """``.wheels/*.whl`` into this interpreter's environment (no index, no dependencies: the folder holds what the
    machine lacks), where the folder exists."""
    wheels = sorted((ROOT / ".wheels").glob("*.whl"))
    if wheels:
        command = [sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps"]
        subprocess.run([*command, *map(str, wheels)], check=False)


def unpack_open3d(target: Path) -> None:
    """``.wheels/open3d.tar.xz`` (``benchmarks/pack_open3d.sh``: the ``open3d`` package without its
    resources and ML ops, and a ``lib/`` of the system libraries it links) unpacked into ``target``, which then
    leads ``PYTHONPATH`` and ``LD_LIBRARY_PATH`` of every step; nothing where the archive is absent."""
    archive = ROOT / ".wheels" / "open3d.tar.xz"
    if not archive.is_file():
        return
    if not (target / "open3d").is_dir():
        target.mkdir(parents=True, exist_ok=True)
        subprocess.run(["tar", "-xJf", str(archive), "-C", str(target)], check=True)
    for variable, path in (("PYTHONPATH", target), ("LD_LIBRARY_PATH", target / "lib")):
        os.environ[variable] = os.pathsep.join(filter(None, (str(path), os.environ.get(variable))))


def gpu_backends() -> str:
    """The latency steps' backends on a GPU: eager and eager bf16, and ``onnx`` where ONNX Runtime has its CUDA
    provider (``onnxruntime-gpu``; its CPU provider's rows would time the CPU, the paper model's at seconds a call)."""
    try:
        import onnxruntime
    except ImportError:
        return "eager,eager-bf16"
    return "eager,eager-bf16" + (",onnx" if "CUDAExecutionProvider" in onnxruntime.get_available_providers() else "")


def steps(args) -> list[Step]:
    """The run's commands, sized by ``args`` (``--smoke``: tiny, on the CPU)."""
    out, smoke = args.out, args.smoke
    on_gpu = "" if smoke else gpu_backends()
    labels = out / "labels"
    trainer = ["trainer=cpu"] if smoke else ["trainer=gpu"]  # precision auto in both (conf/trainer)
    quick = ["trainer.max_steps=2", "trainer.num_sanity_val_steps=0", "metrics.bev_every=0", *smoke_model()]
    length = quick if smoke else [f"trainer.max_time=00:00:{args.minutes:02d}:00"]
    reader = ["dataset.reader.num_sequences=1", "dataset.reader.beams=32"] if smoke else []
    label_common = [f"workers={args.workers}", *reader]
    train_common = [
        f"data.train={labels / 'train'}",
        f"data.val={labels / 'val'}",
        *trainer,
        *length,
        "export.formats=[onnx]" if smoke else "export.formats=[onnx,pt2]",  # pt2: latency_cli's network on the GPU
        "trainer.enable_progress_bar=false",
        f"data.workers={0 if smoke else 4}",
    ]
    train_steps = {"paper": ["experiment=paper"], "small": ["experiment=synthetic_cpu"]}
    test_sequences = max(1, -(-args.test_pairs // 4))
    test = ["split=test", f"dataset.reader.num_sequences={test_sequences}", f"limit={args.test_pairs}", *reader[1:]]
    result = [
        Step(
            out,
            "labels_train",
            ["label.py", f"dataset.reader.num_sequences={args.train_sequences}", "dataset.reader.frames_per_sequence=3"]
            + [f"workers={args.workers}", f"out_dir={labels / 'train'}", *reader[1:]],
        ),
        Step(
            out,
            "labels_val",
            ["label.py", "split=val", *label_common, f"out_dir={labels / 'val'}", *(["limit=1"] if smoke else [])],
        ),
    ]
    for name, recipe in train_steps.items():
        run_dir = out / f"train_{name}"
        result.append(
            Step(
                out,
                f"train_{name}",
                ["train.py", *recipe, *train_common, f"out_dir={run_dir}", "ckpt_path=auto"],
            )
        )
    for name, methods in (("paper", "[ego,icpflow,student]"), ("small", "[student]")):
        eval_dir = out / f"eval_{name}"
        arguments = ["eval.py", *test, f"method={methods}", f"checkpoint={out / f'train_{name}' / 'export'}"]
        result.append(Step(out, f"eval_{name}", [*arguments, f"out_dir={eval_dir}", "bev=0"]))
    for name, model in (("paper", "fastflow3d"), ("small", "fastflow3d_small")):
        latency = ["-m", "benchmarks.bench_student_latency", "--model", model, "--regimes", "given"]
        if smoke:  # no ONNX rows: the export is the step's costliest part, and on a GPU they need onnxruntime-gpu
            latency += ["--device", "cpu", "--runs", "2", "--warmup", "1", "--scans", "uniform", "--points", "3000"]
            latency += ["--backends", "eager,eager-bf16", *SMOKE_LATENCY_MODEL]
        else:
            latency += ["--device", "cuda", "--runs", "100", "--warmup", "10", "--scans", "kitti,av2"]
            latency += ["--backends", on_gpu]
        result.append(Step(out, f"latency_{name}", latency))
    stream = ["-m", "benchmarks.bench_student_latency", "--mode", "stream", "--threads", "2"]
    if smoke:
        stream += ["--regimes", "streamed", "--device", "cpu", "--backends", "eager", "--passes", "1"]
        stream += ["--scans", "kitti", *SMOKE_LATENCY_MODEL]
    else:
        stream += ["--regimes", "streamed,given", "--device", "cuda", "--backends", on_gpu, "--passes", "34"]
    result.append(Step(out, "latency_stream", stream, cpus=2))
    export = args.stream_export or out / "train_small" / "export"
    cli = ["-m", "benchmarks.bench_student_latency", "--mode", "cli", "--export", str(export), "--threads", "2"]
    if smoke:
        cli += ["--device", "cpu", "--backends", "onnxruntime", "--passes", "1", "--scans", "kitti"]
        cli += ["--frames", str(SMOKE_CLI_FRAMES)]
    else:
        cli += ["--device", "cuda", "--backends", "pt2", "--passes", "2", "--scans", "kitti,av2,synthetic"]
    result.append(Step(out, "latency_cli", cli, cpus=2))
    teacher = ["-m", "benchmarks.teacher_backends", "--json", str(out / "teacher.json")]
    if smoke:
        teacher += ["--pairs", "1", "--teacher", "icp.max_points=300", "--teacher", "icp.max_iter=3"]
    elif (args.data / "av2" / "sensor").is_dir():
        teacher += ["--av2", str(args.data / "av2")]
    else:
        teacher += ["--pairs", "8"]
    result.append(Step(out, "teacher", teacher))
    return result


def table_lines(log: Path) -> list[str]:
    """The markdown table lines (and the lines just before each table) a step printed."""
    if not log.is_file():
        return ["(no log)"]
    lines = log.read_text().splitlines()
    keep = [i for i, line in enumerate(lines) if line.startswith("|")]
    picked = sorted({j for i in keep for j in (i - 1, i) if j >= 0})
    return [lines[j] for j in picked] or ["(no table: see the log)"]


def report(args, seconds: dict, failed: list[str]) -> str:
    """``report.md``: every table of the run."""
    from benchmarks.student_report import rows  # after install_wheels: icpflow.evaluation imports hydra

    out = args.out
    lines = [f"# gpu_run ({'smoke, CPU' if args.smoke else 'GPU'}): {time.strftime('%Y-%m-%d %H:%M')}", ""]
    lines += ["| step | wall (s) |", "|---|---|"] + [f"| {k} | {v:.0f} |" for k, v in seconds.items()]
    if failed:
        lines += ["", f"failed: {', '.join(failed)} (logs in {out / 'logs'})"]
    lines += [
        "",
        "## Students after the fixed time",
        "",
        "| student | steps | best val dynamic EPE (m) |",
        "|---|---|---|",
    ]
    for name in ("paper", "small"):
        last = out / f"train_{name}" / "checkpoints" / "last.ckpt"
        steps, best = "-", "-"
        if last.is_file():
            import torch

            checkpoint = torch.load(last, map_location="cpu", weights_only=True, mmap=True)
            steps = checkpoint.get("global_step", "-")
            for key, state in checkpoint.get("callbacks", {}).items():
                if key.startswith("ModelCheckpoint") and state.get("best_model_score") is not None:
                    best = f"{float(state['best_model_score']):.3f}"
        lines.append(f"| {name} | {steps} | {best} |")
    lines += ["", f"## Scores on {args.test_pairs} synthetic test pairs", ""]
    scores = {}
    for name in ("paper", "small"):
        metrics = out / f"eval_{name}" / "metrics.json"
        if metrics.is_file():
            for method, row in rows(metrics).items():
                scores[f"student ({name})" if method == "student" else method] = row
    columns = ["dynamic_fg", "threeway", "static_fg"]
    lines += ["| method | " + " | ".join(columns) + " | / teacher (dynamic) | / ego (dynamic) |", "|---|" + "---|" * 5]
    for method, row in scores.items():
        cells = [f"{row[c]:.3f}" if row.get(c) is not None else "-" for c in columns]
        ratios = [
            f"{row['dynamic_fg'] / scores[ref]['dynamic_fg']:.2f}x" if ref in scores and method != ref else "-"
            for ref in ("icpflow", "ego")
        ]
        lines.append(f"| {method} | " + " | ".join(cells + ratios) + " |")
    for name in ("latency_paper", "latency_small", "latency_stream", "latency_cli", "teacher"):
        lines += ["", f"## {name}", "", *table_lines(out / "logs" / f"{name}.log")]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "outputs" / "gpu_run")
    parser.add_argument("--minutes", type=int, default=3, help="training minutes of each student")
    parser.add_argument("--workers", type=int, default=16, help="labelling processes")
    parser.add_argument("--train-sequences", type=int, default=256, help="synthetic training sequences (2 pairs each)")
    parser.add_argument("--test-pairs", type=int, default=64)
    parser.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data", help="the shipped samples")
    parser.add_argument(
        "--smoke", action="store_true", help="tiny sizes on the CPU: every step runs, in about a minute"
    )
    parser.add_argument("--steps", default=None, help="comma-separated step names to run (default: all)")
    parser.add_argument(
        "--stream-export", type=Path, help="the export latency_cli streams with (default: train_small's own)"
    )
    args = parser.parse_args(argv)
    if importlib.util.find_spec("benchmarks") is None:  # the report reads the scores through benchmarks.student_report
        parser.error("run from the checkout's root as: python3 -m benchmarks.gpu_run ...")
    if args.smoke:
        args.train_sequences, args.test_pairs, args.workers, args.minutes = 2, 1, 1, 0
    args.out = args.out.resolve()
    if not args.smoke:
        install_wheels()
        unpack_open3d(args.out / "open3d")
    seconds, failed = {}, []
    chosen = steps(args)
    if args.steps:
        names = [name.strip() for name in args.steps.split(",") if name.strip()]
        unknown = sorted(set(names) - {step.name for step in chosen})
        if unknown:
            parser.error(f"--steps: unknown {', '.join(unknown)}; steps: {', '.join(step.name for step in chosen)}")
        chosen = [step for step in chosen if step.name in names]
    for step in chosen:
        if not step.run(seconds):
            failed.append(step.name)
    text = report(args, seconds, failed)
    write_text_atomic(args.out / "report.md", text)
    write_text_atomic(args.out / "seconds.json", json.dumps(seconds, indent=1))
    print(text)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
