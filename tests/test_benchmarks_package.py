"""``benchmarks/`` is a package run as ``python -m benchmarks.<script>``: no script puts a folder on Python's path,
the project's packages never import it, and ``benchmarks/README.md`` names every module it holds."""

import ast
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BENCHMARKS = REPO / "benchmarks"


def test_no_benchmark_touches_sys_path():
    touching = [
        str(path.relative_to(REPO))
        for path in BENCHMARKS.rglob("*.py")
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Attribute) and node.attr == "path" and getattr(node.value, "id", None) == "sys"
    ]
    assert touching == []


def test_the_packages_never_import_benchmarks():
    importing = []
    for package in ("icpflow", "fastflow3d"):
        for path in (REPO / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
                names += [node.module or ""] if isinstance(node, ast.ImportFrom) else []
                importing += [str(path.relative_to(REPO)) for name in names if name.split(".")[0] == "benchmarks"]
    assert importing == []


def test_the_readme_names_every_module():
    named = set(re.findall(r"`(?:studies/)?(\w+)(?:\.py)?`", (BENCHMARKS / "README.md").read_text()))
    modules = {path.stem for path in BENCHMARKS.rglob("*.py") if path.stem != "__init__"}
    assert modules - named == set()
