"""The report of an evaluation: the printed table, ``metrics.json`` and ``metrics.csv``, one schema for one frame
gap or several (one gap is a list of one).

``metrics.json`` (NaN written as null)::

    {"schema_version": 2,
     "complete": true | false,          # false: the run stopped early, "stopped" says why; pairs lists what was scored
     "stopped": null | "terminated (SIGTERM)" | "interrupted (Ctrl-C)",
     "horizons": [1, ...],
     "table": {"weighting": "point_weighted" | "per_pair", "rows": [one row per (method, k), see table_rows]},
     "methods": {name: {"<k>": summary}},   # scoring.MethodScores.summary: both weightings, Threeway, bucketed
     "pairs": {"<k>": [sample ids scored]},
     "failures": [{"index", "sample_id", "horizon", "reason"}],
     "settings": {crop, include_ground, relative_to, dynamic_speed, bucketed_classes, horizons},
     ...extra (eval.py: "dataset", "split", "config", and "method_descriptions": what a method says it runs)}

``metrics.csv``: one row per (method, k, metric): the paper's rows of both weightings, Threeway and bucketed EPE,
seconds per pair and the mean dt. Readers: :func:`read_metrics` and :func:`method_summary`.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import tempfile
from pathlib import Path

from icpflow.core.atomic import WriteError, write_text_atomic
from icpflow.core.files import read_text
from icpflow.evaluation import metrics
from icpflow.evaluation.run import EvaluationResult

SCHEMA_VERSION = 2
SPLITS = ("dynamic_fg", "static_fg", "static_bg")
PAPER_COLUMNS = ("EPE", "AccS", "AccR")
CSV_COLUMNS = (
    "method",
    "horizon",
    "metric",
    "EPE",
    "AccS",
    "AccR",
    "Outliers",
    "count",
    "dynamic_normalized_epe",
    "value",
)
#: bytes written (and removed) by :func:`check_writable`: room for metrics.json, metrics.csv and a few pictures
PROBE_BYTES = 1 << 20


def table_rows(result: EvaluationResult, weighting: str = "point_weighted") -> list[dict]:
    """One row per (method, horizon k), methods in order, k ascending: the mean real dt (s) of the pairs, EPE (m),
    Acc-S and Acc-R of every category (``metrics.CATEGORIES``), Threeway EPE, mean bucketed dynamic normalised EPE,
    seconds per pair and the pairs scored."""
    rows = []
    for name, per_gap in result.summaries.items():
        for horizon in result.horizons:
            summary = per_gap[horizon]
            table = summary["paper"][weighting]
            rows.append(
                {
                    "method": name,
                    "horizon": horizon,
                    "dt_s": summary["dt_s"],
                    **{f"{c}_{category}": table[category][c] for category in metrics.CATEGORIES for c in PAPER_COLUMNS},
                    "threeway_EPE": summary["threeway"]["threeway"] if summary["threeway"] else math.nan,
                    "dynamic_normalized_EPE": (
                        summary["bucketed"]["mean"]["dynamic_normalized_epe"] if summary["bucketed"] else math.nan
                    ),
                    "seconds_per_pair": summary["seconds_per_pair"],
                    "pairs": summary["pairs"],
                }
            )
    return rows


def format_table(rows: list[dict]) -> str:
    """:func:`table_rows` in the paper's layout: per (method, k) the dt, EPE / Acc-S / Acc-R of dynamic fg, static
    fg, static bg, seconds per pair, Threeway EPE and mean dynamic normalised EPE."""
    width = max(10, *(len(row["method"]) + 1 for row in rows))
    splits = "".join(f"| {s:^26} " for s in SPLITS)
    head = f"{'method':<{width}}|  k | dt (s) {splits}| s/pair | 3-way  | dyn.norm"
    sub = f"{'':<{width}}|    |        " + "| EPE(m)   Acc-S    Acc-R  " * len(SPLITS) + "|        |  EPE   |  EPE"
    lines = [head, sub]
    for row in rows:
        cells = "".join("| " + " ".join(f"{row[f'{c}_{s}']:>8.4f}" for c in PAPER_COLUMNS) + " " for s in SPLITS)
        lines.append(
            f"{row['method']:<{width}}| {row['horizon']:>2} | {row['dt_s']:6.3f} {cells}"
            f"| {row['seconds_per_pair']:6.3f} | {row['threeway_EPE']:6.4f} | {row['dynamic_normalized_EPE']:6.4f}"
        )
    return "\n".join(lines)


def metrics_document(result: EvaluationResult, weighting: str = "point_weighted", extra: dict | None = None) -> dict:
    """The content of ``metrics.json`` (see the module docstring)."""
    return {
        "schema_version": SCHEMA_VERSION,
        "complete": result.complete,
        "stopped": result.stopped,
        "horizons": result.horizons,
        "table": {"weighting": weighting, "rows": table_rows(result, weighting)},
        "methods": {name: {str(k): s for k, s in per_gap.items()} for name, per_gap in result.summaries.items()},
        "pairs": {str(k): ids for k, ids in result.pairs.items()},
        "failures": result.failures,
        "settings": result.settings,
    } | (extra or {})


def csv_rows(result: EvaluationResult) -> list[dict]:
    """Flat rows, one per (method, k, metric): every paper row of both weightings, Threeway, bucketed per class,
    seconds per pair and dt (s) (the last two in ``value``)."""
    rows = []
    for name, per_gap in result.summaries.items():
        for horizon, summary in per_gap.items():
            key = {"method": name, "horizon": horizon}
            for weighting, table in summary["paper"].items():
                for category, values in table.items():
                    rows.append(key | {"metric": f"paper/{weighting}/{category}", **values})
            for key_name, value in (summary["threeway"] or {}).items():
                rows.append(key | {"metric": f"threeway/{key_name}", "EPE": value})
            for cls, values in (summary["bucketed"] or {"per_class": {}})["per_class"].items():
                rows.append(
                    key
                    | {
                        "metric": f"bucketed/{cls}",
                        "EPE": values["static_epe"],
                        "dynamic_normalized_epe": values["dynamic_normalized_epe"],
                    }
                )
            rows.append(key | {"metric": "seconds_per_pair", "value": summary["seconds_per_pair"]})
            rows.append(key | {"metric": "dt_s", "value": summary["dt_s"]})
    return rows


def check_writable(out_dir) -> None:
    """Make ``out_dir`` and write, fsync and remove :data:`PROBE_BYTES` there, so a read-only or full place is
    found before the long work; raises :class:`WriteError` naming ``out_dir`` and the cause."""
    out_dir = Path(out_dir)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out_dir, prefix=".eval-write-check-") as probe:
            probe.write(b"\0" * PROBE_BYTES)
            probe.flush()
            os.fsync(probe.fileno())
    except OSError as error:
        raise WriteError(f"out_dir={out_dir}: cannot write there ({error.strerror or error})") from None


def write_results(
    result: EvaluationResult, out_dir, weighting: str = "point_weighted", extra: dict | None = None
) -> tuple[Path, Path]:
    """``metrics.json`` and ``metrics.csv`` under ``out_dir``, each written atomically (a :class:`WriteError`
    names the file and the cause)."""
    out_dir = Path(out_dir)
    json_path, csv_path = out_dir / "metrics.json", out_dir / "metrics.csv"
    write_text_atomic(json_path, metrics_json(result, weighting, extra), make_parents=True)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, CSV_COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(csv_rows(result))
    write_text_atomic(csv_path, buffer.getvalue())
    return json_path, csv_path


def metrics_json(result: EvaluationResult, weighting: str = "point_weighted", extra: dict | None = None) -> str:
    """:func:`metrics_document` as JSON text (NaN as null)."""
    return json.dumps(_nan_to_none(metrics_document(result, weighting, extra)), indent=2) + "\n"


def read_metrics(path, partial_ok: bool = False) -> dict:
    """An eval.py ``metrics.json`` (``path``: the file or its out_dir); raises ValueError for another schema, and
    for a partial one unless ``partial_ok``."""
    path = Path(path)
    path = path / "metrics.json" if path.is_dir() else path
    document = json.loads(read_text(path))
    if document.get("schema_version") != SCHEMA_VERSION:
        raise ValueError(f"{path}: not an eval.py metrics.json of schema {SCHEMA_VERSION}; rerun eval.py")
    if not document["complete"] and not partial_ok:
        raise ValueError(f"{path}: partial ({document['stopped']}); rerun the eval.py command that wrote it")
    return document


def is_complete(path) -> bool:
    """Whether ``path`` (a metrics.json or its out_dir) holds a complete evaluation of this schema."""
    try:
        read_metrics(path)
    except (OSError, ValueError):
        return False
    return True


def method_summary(document: dict, method: str, horizon: int | None = None) -> dict:
    """``method``'s summary at frame gap ``horizon`` (default: the first gap scored) in a metrics.json document."""
    return document["methods"][method][str(document["horizons"][0] if horizon is None else horizon)]


def _nan_to_none(value):
    if isinstance(value, dict):
        return {k: _nan_to_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_nan_to_none(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
