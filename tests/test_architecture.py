"""The import graph of the two packages (read from the code with ``ast``, imports inside functions included): no
circle anywhere, and no arrow from the teacher wing (``icpflow``) to the student wing (``fastflow3d``). One way to
stop (issue 32): signal handlers installed by ``icpflow.entry`` only, every entry point stopping and reporting through
it, messages folded by ``icpflow.entry.one_line`` only, and ``icpflow.entry`` cheap to import."""

import ast
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("icpflow", "fastflow3d")


def module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph() -> dict[str, set[str]]:
    """Module -> the modules of the two packages it imports (``from a import b`` names ``a.b`` when it is a
    module, else ``a``; relative imports resolved)."""
    files = {module_name(path): path for package in PACKAGES for path in (REPO / package).rglob("*.py")}
    graph = {}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets.update(alias.name for alias in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join([*anchor, *([base] if base else [])])
                for alias in node.names:
                    targets.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in files else base)
        graph[name] = {target for target in targets if target in files and target != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan's algorithm)."""
    index, low, stack, on_stack, found, counter = {}, {}, [], set(), [], [0]

    def visit(node):
        index[node] = low[node] = counter[0]
        counter[0] += 1
        stack.append(node)
        on_stack.add(node)
        for target in sorted(graph[node]):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_the_graph_is_read_from_the_code():
    graph = import_graph()
    assert {"fastflow3d.artifact"} <= graph["fastflow3d.export"] & graph["fastflow3d.predictor"]
    assert "icpflow.teacher.config" in graph["icpflow.evaluation.cli"]  # a lazy import inside a function counts
    assert "icpflow.frames" in graph["icpflow"]  # the package's __init__
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_circle():
    assert cycles(import_graph()) == []


def test_the_teacher_wing_never_imports_the_student():
    graph = import_graph()
    arrows = [
        (source, target)
        for source, targets in graph.items()
        if source.startswith("icpflow")
        for target in targets
        if target.startswith("fastflow3d")
    ]
    assert arrows == []


# ---------------------------------------------------------------------------------------- one way to stop (issue 32)

#: the scripts a user runs, besides the console script fastflow3d-infer (fastflow3d/infer.py)
SCRIPTS = ("label.py", "train.py", "eval.py", "export.py")


def sources() -> dict[str, str]:
    """Relative path -> text of every module of the two packages and of the scripts."""
    paths = [*(path for package in PACKAGES for path in (REPO / package).rglob("*.py")), *(REPO / s for s in SCRIPTS)]
    return {str(path.relative_to(REPO)): path.read_text() for path in paths}


def entry_names(text: str) -> set[str]:
    """The names a module imports from icpflow.entry."""
    return {
        alias.name
        for node in ast.walk(ast.parse(text))
        if isinstance(node, ast.ImportFrom) and node.module == "icpflow.entry"
        for alias in node.names
    }


def test_signal_handlers_are_installed_by_icpflow_entry_only():
    """Every entry point and the training callback install their SIGINT/SIGTERM handlers through
    ``icpflow.entry.on_signals`` (``stop_on_signals``); the one other call: a labelling worker ignoring Ctrl-C."""
    calls = []
    for name, text in sources().items():
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ImportFrom) and node.module == "signal":
                calls += [(name, f"from signal import {alias.name}") for alias in node.names]
            elif isinstance(node, ast.Call) and ast.unparse(node.func) == "signal.signal":
                calls.append((name, ast.unparse(node)))
    outside = [call for call in calls if call[0] != "icpflow/entry.py"]
    assert outside == [("icpflow/labelling/executors.py", "signal.signal(signal.SIGINT, signal.SIG_IGN)")]
    assert any(name == "icpflow/entry.py" for name, _ in calls)  # the check reads the calls


def test_every_entry_point_stops_and_reports_through_icpflow_entry():
    texts = sources()
    for script in SCRIPTS:
        assert {"reported", "run"} <= entry_names(texts[script]), script
    assert {"exit_status", "stop_on_signals"} <= entry_names(texts["fastflow3d/infer.py"])
    assert "exit_status" in entry_names(texts["fastflow3d/export.py"])  # run_export, export.py's body
    for module in ("icpflow/labelling/cli.py", "icpflow/evaluation/cli.py", "fastflow3d/training.py"):
        assert "stop_on_signals" in entry_names(texts[module]), module
    assert "on_signals" in entry_names(texts["fastflow3d/callbacks.py"])


def test_messages_are_folded_onto_one_line_by_icpflow_entry_only():
    folded = re.compile(r"""(['"]) \1\.join\(str\(""")
    found = [name for name, text in sources().items() if folded.search(text)]
    assert found == ["icpflow/entry.py"]  # one_line itself


def test_importing_icpflow_entry_stays_cheap():
    """Every module may import icpflow.entry (it imports nothing of the packages but icpflow.settings, which imports
    none): no heavy library comes with it."""
    code = "import sys, icpflow.entry; print(' '.join(sorted(m for m in sys.modules if '.' not in m)))"
    loaded = set(subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True).stdout.split())
    assert "icpflow" in loaded and not loaded & {"torch", "lightning", "hydra", "omegaconf", "numba", "scipy"}
    assert "icpflow.entry" in import_graph() and import_graph()["icpflow.entry"] <= {"icpflow.settings"}
    assert not import_graph()["icpflow.settings"]
