"""The issue-19 table of one ``eval.py`` run: dynamic-foreground, Threeway and static-foreground EPE and the bucketed
normalised EPE per class of each method, and each method's ratio to the teacher (``icpflow``) and to ego-only.

    .venv/bin/python -m benchmarks.student_report <eval out_dir>/metrics.json
"""

from __future__ import annotations

import argparse
from pathlib import Path

from icpflow.evaluation import method_summary, read_metrics


def rows(metrics_json: Path) -> dict[str, dict[str, float]]:
    """method -> {"dynamic_fg", "threeway", "static_fg", "bucketed/<class>"...} from an eval.py metrics.json."""
    out = {}
    document = read_metrics(metrics_json)
    for method in document["methods"]:
        summary = method_summary(document, method)
        table = summary["paper"]["point_weighted"]
        row = {
            "dynamic_fg": table["dynamic_fg"]["EPE"],
            "threeway": summary["threeway"]["threeway"],
            "static_fg": table["static_fg"]["EPE"],
        }
        for name, values in ((summary.get("bucketed") or {}).get("per_class") or {}).items():
            row[f"bucketed/{name}"] = values["dynamic_normalized_epe"]
        out[method] = row
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("metrics", type=Path, help="an eval.py out_dir's metrics.json")
    table = rows(parser.parse_args().metrics)
    columns = list(dict.fromkeys(column for row in table.values() for column in row))
    print("| method | " + " | ".join(columns) + " |")
    print("|---|" + "---|" * len(columns))
    for method, row in table.items():
        print(f"| {method} | " + " | ".join("-" if row.get(c) is None else f"{row[c]:.3f}" for c in columns) + " |")
    for reference in ("icpflow", "ego"):
        if reference in table and "student" in table:
            cells = []
            for column in columns:
                ours, theirs = table["student"].get(column), table[reference].get(column)
                cells.append(f"{ours / theirs:.2f}x" if ours is not None and theirs else "-")
            print(f"| student / {reference} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
