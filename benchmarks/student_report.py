"""The issue-19 table of one ``eval.py`` run: dynamic-foreground, Threeway and static-foreground EPE and the bucketed
normalised EPE per class of each method, and each method's ratio to the teacher (``icpflow``) and to ego-only.

    .venv/bin/python benchmarks/student_report.py <eval out_dir>/metrics.json
"""

from __future__ import annotations

import sys
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
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    table = rows(Path(sys.argv[1]))
    columns = list(next(iter(table.values())))
    print("| method | " + " | ".join(columns) + " |")
    print("|---|" + "---|" * len(columns))
    for method, row in table.items():
        print(f"| {method} | " + " | ".join(f"{row[c]:.3f}" for c in columns) + " |")
    for reference in ("icpflow", "ego"):
        if reference in table and "student" in table:
            ratios = [
                table["student"][c] / table[reference][c] if table[reference][c] else float("nan") for c in columns
            ]
            print(f"| student / {reference} | " + " | ".join(f"{r:.2f}x" for r in ratios) + " |")


if __name__ == "__main__":
    main()
