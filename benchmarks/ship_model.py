"""Rebuild the model that ships inside the package (``fastflow3d/artifact/models/synthetic_cpu/``,
``fastflow3d.artifact.shipped``): label, train ``experiment=synthetic_cpu``, score, package, write its card.

    python -m benchmarks.ship_model --work /tmp/ship            # everything, about an hour on 2 cores
    python -m benchmarks.ship_model --work /tmp/ship --package  # package a run already in --work (no training)

Steps, each skipped where ``--work`` already holds its result: 1,024 train pairs (512 sequences of 3 frames) and the
val split labelled by the teacher (``label.py``), ``train.py experiment=synthetic_cpu seed=S``, ``eval.py split=test``
on the 64 synthetic test pairs (ego-only, the teacher, the student in float32 and as ``--precision auto`` runs it, the
student refined) and on the real Argoverse 2 pair in ``../shared/data/av2`` where it is present. Packaging copies the
export's ONNX files (float32 and int8, not the ``.pt2``: ONNX Runtime runs them), rewrites ``metadata.json`` (the files
it lists, the ``shipped`` entry, the checkpoint named by its hash, not by a path on the building machine) and writes
``MODEL_CARD.md`` from the scores.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from benchmarks.common import DATA, ROOT, cpu_name
from fastflow3d.artifact.file_format import METADATA_NAME
from fastflow3d.artifact.shipped import CARD_NAME, SHIPPED_NAME
from icpflow.core.atomic import write_text_atomic
from icpflow.evaluation import is_complete, method_summary, read_metrics

TARGET = ROOT / "fastflow3d" / "artifact" / "models" / SHIPPED_NAME
SHIPPED_FILES = ("onnx", "onnx_int8")
TEST_METHODS = "[ego,icpflow,student,student+refine]"
TEST_PAIRS = "dataset.reader.num_sequences=16"  # the 64 synthetic test pairs every recipe is scored on
CATEGORIES = ("dynamic_fg", "static_fg", "static_bg", "overall")


def commands(work: Path, seed: int) -> dict[str, list[str]]:
    """Each step's command line (run from the checkout's root)."""
    python = sys.executable
    export = work / "train" / "export"
    return {
        "label_train": [python, "label.py", "split=train", "dataset.reader.num_sequences=512",
                        "dataset.reader.frames_per_sequence=3", f"out_dir={work / 'train1024'}"],
        "label_val": [python, "label.py", "split=val", f"out_dir={work / 'val'}"],
        "train": [python, "train.py", "experiment=synthetic_cpu", f"seed={seed}", f"data.train={work / 'train1024'}",
                  f"data.val={work / 'val'}", f"out_dir={work / 'train'}"],
        "test_f32": [python, "eval.py", "split=test", TEST_PAIRS, f"method={TEST_METHODS}", f"checkpoint={export}",
                     "precision=f32", f"out_dir={work / 'eval_test_f32'}"],
        "test_auto": [python, "eval.py", "split=test", TEST_PAIRS, "method=[student]", f"checkpoint={export}",
                      "precision=auto", f"out_dir={work / 'eval_test_auto'}"],
        "av2": [python, "eval.py", "dataset=av2", f"dataset.root={DATA / 'av2'}", "split=val",
                "method=[ego,icpflow,student]", f"checkpoint={export}", "precision=f32",
                f"out_dir={work / 'eval_av2'}"],
    }  # fmt: skip


def done(step: str, work: Path) -> bool:
    """Whether ``work`` already holds ``step``'s result."""
    results = {"label_train": work / "train1024", "label_val": work / "val", "train": work / "train" / "export"}
    if step in results:
        return (results[step] / ("index.json" if step.startswith("label") else METADATA_NAME)).is_file()
    return is_complete(work / f"eval_{step}")


def run_steps(work: Path, seed: int) -> dict[str, float]:
    """Run every step not done yet; returns each run step's seconds."""
    seconds = {}
    for step, command in commands(work, seed).items():
        if done(step, work) or (step == "av2" and not (DATA / "av2").is_dir()):
            continue
        print(f"ship_model: {step}: {' '.join(command)}", flush=True)
        start = time.perf_counter()
        subprocess.run(command, cwd=ROOT, check=True)
        seconds[step] = time.perf_counter() - start
        times = work / "seconds.json"  # kept for a later --package run
        write_text_atomic(times, json.dumps({**step_seconds(work), step: seconds[step]}))
    return step_seconds(work)


def step_seconds(work: Path) -> dict[str, float]:
    """The seconds of each step run so far in ``work``."""
    times = work / "seconds.json"
    return json.loads(times.read_text()) if times.is_file() else {}


def scores(metrics_path: Path) -> dict[str, dict[str, float]]:
    """Method -> category -> point-weighted EPE (m) of an ``eval.py`` metrics.json (its first horizon); {} where it
    is absent."""
    if not is_complete(metrics_path):
        return {}
    document = read_metrics(metrics_path)
    return {
        method: {c: method_summary(document, method)["paper"]["point_weighted"][c]["EPE"] for c in CATEGORIES}
        for method in document["methods"]
    }


def score_table(table: dict[str, dict[str, float]]) -> str:
    """A markdown table of :func:`scores`."""
    lines = [
        "| method | dynamic foreground | static foreground | static background | overall |",
        "|---|---|---|---|---|",
    ]
    for method, row in table.items():
        lines.append(f"| {method} | " + " | ".join(f"{row[category]:.4f}" for category in CATEGORIES) + " |")
    return "\n".join(lines)


def shipped_metadata(export: Path, work: Path, command: list[str], commit: str) -> dict:
    """The export's metadata as shipped: only the files that ship, the checkpoint by name and hash, the ``shipped``
    entry."""
    metadata = json.loads((export / METADATA_NAME).read_text())
    metadata["files"] = {kind: entry for kind, entry in metadata["files"].items() if kind in SHIPPED_FILES}
    source = metadata.get("source_checkpoint") or {}
    if source.get("path"):
        source["path"] = Path(source["path"]).name
    metadata["shipped"] = {
        "name": SHIPPED_NAME,
        "card": CARD_NAME,
        "commit": commit,
        "command": " ".join(part.replace(str(work), "<work>") for part in command),
    }
    return metadata


def card(work: Path, metadata: dict, commit: str, host: str, train_minutes: float | None) -> str:
    """MODEL_CARD.md: what the model is, how it was made, what it scores, what it is not."""
    test, auto, av2 = (scores(work / name) for name in ("eval_test_f32", "eval_test_auto", "eval_av2"))
    if "student" in auto:
        test[f"student, as `--precision auto` ran it here ({auto_precision(work)})"] = auto["student"]
    minutes = f"{train_minutes:.0f} min of wall time" if train_minutes else "(not timed here)"
    real = score_table(av2) if av2 else "(not scored: ../shared/data/av2 was absent)"
    return CARD_TEMPLATE.format(
        version=metadata.get("package_version"),
        commit=commit,
        host=host,
        minutes=minutes,
        command=metadata["shipped"]["command"],
        test=score_table(test),
        real=real,
        sha=(metadata.get("source_checkpoint") or {}).get("sha256", "?"),
    )


def auto_precision(work: Path) -> str:
    """The network ``--precision auto`` ran in the auto evaluation, as ``eval.py`` recorded it (``int8 network,
    onnxruntime``)."""
    descriptions = read_metrics(work / "eval_test_auto").get("method_descriptions", {})
    return str(descriptions.get("student", "auto"))


CARD_TEMPLATE = """# The shipped model: `synthetic_cpu`'s student (icpflow {version})

What `fastflow3d-infer SCANS` and `Predictor.load()` run when no model is named. FastFlow3D's small network (1.8 M
parameters, 0.5 m pillars over +-32 m, a 7 x 7 cost volume at the 1 m level, ZeroFlow's linear head), trained by
distillation on the ICP-Flow teacher's pseudo-labels. Files: `fastflow3d.onnx` (float32), `fastflow3d.int8.onnx`
(int8, chosen by `--precision auto` on CPUs with int8 dot products), `metadata.json` (grid, input contract, flow
convention: FULL flow in the ego frame of scan 0, metres per frame).

## How it was made

- Commit `{commit}`, on {host}, 2 cores; training took {minutes} (the recipe on a quiet machine:
  [BENCHMARKS.md](../../../../BENCHMARKS.md#student-scores-per-recipe)).
- Data: the teacher's labels of 1,024 synthetic pairs (512 sequences of 3 frames); validation: the synthetic val
  split.
- Training: `{command}` (3,900 steps of batch 4, `precision: auto`); the checkpoint's sha256 `{sha}`.
- Rebuilt by `python -m benchmarks.ship_model --work DIR` from a checkout.

## What it scores

EPE (m, point-weighted) on the 64 synthetic test pairs (`eval.py split=test`; the dataset's ego motion and ground
given to every method):

{test}

On the real Argoverse 2 pair shipped beside the checkout (`../shared/data/av2`, one pair, its ground truth):

{real}

## What it is not

- It has seen the synthetic world only (a simulated 64-beam LiDAR, boxes for cars, pedestrians, walls and poles).
  On real scans it runs and its flow is plausible on moving cars, but it moves static structure more than the
  teacher does: for real data, label your own drives (`label.py dataset=...`) and train on them.
- Slow objects (pedestrians, under about 3 m/s) get a small fraction of their motion: a pillar is 0.5 m.
- It sees +-32 m around the sensor, non-ground points only; everything else gets the ego motion.
- Its int8 network, which `--precision auto` runs on CPUs with int8 dot products, is quicker but less exact than
  the float32 one (the table above); `--precision f32` / `Predictor.load(precision="f32")` runs the float32 one.
- Licence: the weights are the project's (MIT); they were trained on synthetic data only, no third-party dataset.
"""


def source_commit() -> str:
    """The checkout's commit, marked where tracked files differ from it."""
    git = ["git", "-C", str(ROOT)]
    commit = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    changed = subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True)
    return (commit or "unknown") + (" with local changes" if changed.stdout.strip() else "")


def package(work: Path, seed: int, seconds: dict[str, float]) -> Path:
    """Copy the shipped files from ``work``'s export into :data:`TARGET` with the rewritten metadata and the card."""
    export = work / "train" / "export"
    commit = source_commit()
    metadata = shipped_metadata(export, work, commands(work, seed)["train"][1:], commit)
    TARGET.mkdir(parents=True, exist_ok=True)
    for entry in metadata["files"].values():
        shutil.copyfile(export / entry["path"], TARGET / entry["path"])
    write_text_atomic(TARGET / METADATA_NAME, json.dumps(metadata, indent=2) + "\n")
    minutes = seconds["train"] / 60 if "train" in seconds else None
    write_text_atomic(TARGET / CARD_NAME, card(work, metadata, commit, cpu_name(), minutes))
    return TARGET


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True, help="where the labels, the run and the scores go")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--package", action="store_true", help="only package what --work holds (no new steps)")
    args = parser.parse_args(argv)
    work = args.work.resolve()
    seconds = step_seconds(work) if args.package else run_steps(work, args.seed)
    print(f"ship_model: packaged -> {package(work, args.seed, seconds)}")


if __name__ == "__main__":
    main()
