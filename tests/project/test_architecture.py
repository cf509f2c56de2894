"""The import graph of the two packages (read from the code with ``ast``, imports inside functions included): no
circle anywhere, no arrow from the shared core and teacher (``icpflow``) to the student wing (``fastflow3d``), each
package's rooms importing one way (``ROOMS``, ``ICPFLOW_ROOMS``; one place opens a model file,
``fastflow3d.artifact.engines``), and the student reaching the teacher through its public modules only. One way to
stop (issue 32): signal handlers installed by ``icpflow.core.errors_and_signals`` only, every entry point stopping and
reporting through it, messages folded by ``icpflow.core.errors_and_signals.one_line`` only, and
``icpflow.core.errors_and_signals`` cheap to import."""

import ast
import functools
import re
import subprocess
import sys
from pathlib import Path

import pytest

from helpers.data import REPO

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
    assert (
        "fastflow3d.artifact.engines"
        in graph["fastflow3d.artifact.export"] & graph["fastflow3d.inference.model_loading"]
    )
    assert "icpflow.teacher.config" in graph["icpflow.evaluation.cli"]  # a lazy import inside a function counts
    assert "icpflow.core.frame_pair" in graph["icpflow"]  # the package's __init__
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


# ------------------------------------------------------------------------------- the student wing's rooms (issue 46)

#: each room of ``fastflow3d`` and the rooms it may import: network <- artifact <- inference, network <- training ->
#: artifact; inference and training never import each other, network imports no other room
ROOMS = {
    "network": set(),
    "artifact": {"network"},
    "inference": {"network", "artifact"},
    "training": {"network", "artifact"},
}


#: each room of ``icpflow`` and the rooms it may import: core <- scans <- datasets <- teacher; shards <- core; the
#: labelling and the evaluation on top (the evaluation reads the labelling's ``dataset`` schema); pictures on core
ICPFLOW_ROOMS = {
    "core": set(),
    "scans": {"core"},
    "datasets": {"core", "scans"},
    "teacher": {"core", "scans", "datasets"},
    "shards": {"core"},
    "labelling": {"core", "scans", "datasets", "teacher", "shards"},
    "evaluation": {"core", "scans", "datasets", "teacher", "shards", "labelling", "viz"},
    "viz": {"core"},
}

#: the teacher's modules the student wing may import: the pipeline's config, the registration's API, the checks the
#: refinement applies, a sample's teacher flow (agreement labels) and the kernels' warm-up
TEACHER_API = {
    "icpflow.teacher",
    "icpflow.teacher.checks",
    "icpflow.teacher.config",
    "icpflow.teacher.long_horizon",
    "icpflow.teacher.registration",
    "icpflow.teacher.warmup",
}


def room_of(module: str) -> str | None:
    """The room of a module (``<package>.<room>.<module>``), None for a package itself."""
    parts = module.split(".")
    return parts[1] if parts[0] in PACKAGES and len(parts) > 1 else None


def room_arrows(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    """The imports between two rooms of one package that its rooms' table does not allow."""
    doors = {"fastflow3d": ROOMS, "icpflow": ICPFLOW_ROOMS}
    return sorted(
        (source, target)
        for source, targets in graph.items()
        for target in targets
        if source.split(".")[0] == target.split(".")[0]
        if room_of(source) and room_of(target) and room_of(source) != room_of(target)
        if room_of(target) not in doors[source.split(".")[0]].get(room_of(source), set())
    )


@functools.cache
def shims() -> frozenset[str]:
    """The last release's module paths kept until 0.3 (``icpflow.core.deprecation``;
    ``tests/project/test_public_api.py`` checks each): modules that call ``warn_moved`` in their body and define no
    function or class, only re-export. They lie
    outside the rooms (a tiny file at the old path) and may import any room; nothing imports them."""
    found = set()
    for package in PACKAGES:
        for path in (REPO / package).rglob("*.py"):
            body = ast.parse(path.read_text()).body
            warns = any(isinstance(node, ast.Expr) and ast.unparse(node).startswith("warn_moved(") for node in body)
            if warns and not any(isinstance(node, (ast.FunctionDef, ast.ClassDef)) for node in body):
                found.add(module_name(path))
    return frozenset(found)


@pytest.mark.parametrize("package, rooms", [("fastflow3d", ROOMS), ("icpflow", ICPFLOW_ROOMS)])
def test_every_module_lives_in_a_room(package, rooms):
    modules = [name for name in import_graph() if name.split(".")[0] == package and name not in shims()]
    assert {room_of(name) for name in modules} - {None} == set(rooms)
    assert [name for name in modules if room_of(name) is None] == [package]  # the package's face only


def test_the_student_reaches_the_teacher_through_its_public_modules():
    graph = import_graph()
    reached = {
        target
        for source, targets in graph.items()
        if source.startswith("fastflow3d") and source not in shims()
        for target in targets
        if target.startswith("icpflow.teacher")
    }
    assert reached <= TEACHER_API and "icpflow.teacher.registration" in reached  # the refinement's registration


def test_the_rooms_import_one_way():
    graph = import_graph()
    assert room_arrows({name: targets for name, targets in graph.items() if name not in shims()}) == []
    assert room_arrows({"fastflow3d.inference.a": {"fastflow3d.training.b"}, "fastflow3d.network.c": set()}) == [
        ("fastflow3d.inference.a", "fastflow3d.training.b")
    ]
    assert room_arrows({"icpflow.scans.a": {"icpflow.teacher.b", "icpflow.core.c"}}) == [
        ("icpflow.scans.a", "icpflow.teacher.b")
    ]
    assert "icpflow.scans.odometry" in graph["icpflow.teacher.pipeline"]  # icpflow's arrows are read too
    # the arrows between rooms are read: the trainer exports, a checkpoint builds the network
    assert "fastflow3d.artifact.export" in graph["fastflow3d.training.trainer"]
    assert "fastflow3d.network.model" in graph["fastflow3d.artifact.checkpoint"]


def test_nothing_imports_a_shim():
    """The last release's paths are for its users only: no module of the two packages imports one (they import
    today's paths), and none lies in a room."""
    graph, old = import_graph(), shims()
    assert {"fastflow3d.predictor", "fastflow3d.infer", "icpflow.entry"} <= old  # the check reads the shims
    assert sorted((source, target) for source, targets in graph.items() for target in targets & old) == []
    assert {name for name in old if room_of(name) in set(ROOMS) | set(ICPFLOW_ROOMS)} <= {
        # old modules inside a room whose new home is the same room
        "icpflow.datasets.io",
        "icpflow.datasets.sequence",
        "icpflow.teacher.icp",
        "icpflow.teacher.neighbours",
        "icpflow.teacher.registration_cpu",
        "icpflow.teacher.registration_torch",
        "icpflow.teacher.tracker",
    }


#: the calls that open a model file in an engine (ONNX Runtime, OpenVINO, torch.export, TorchScript)
OPENERS = ("InferenceSession", "compile_model", "read_model", "torch.export.load", "torch.jit.load")


def test_one_module_opens_model_files():
    """The Predictor, the export's parity check and the latency benchmark open a model file through
    ``fastflow3d.artifact.engines.load_network`` only."""
    found = set()
    for name, text in sources().items():
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.Call) and ast.unparse(node.func).endswith(OPENERS):
                found.add(name)
    assert found == {"fastflow3d/artifact/engines.py"}
    benchmark = (REPO / "benchmarks" / "bench_student_latency.py").read_text()
    assert not any(opener in benchmark for opener in OPENERS) and "load_network(" in benchmark


# ---------------------------------------------------------------------------------------- one way to stop (issue 32)

#: the scripts a user runs, besides the console script fastflow3d-infer (fastflow3d/inference/cli.py)
SCRIPTS = ("label.py", "train.py", "eval.py", "export.py")


def sources() -> dict[str, str]:
    """Relative path -> text of every module of the two packages and of the scripts."""
    paths = [*(path for package in PACKAGES for path in (REPO / package).rglob("*.py")), *(REPO / s for s in SCRIPTS)]
    return {str(path.relative_to(REPO)): path.read_text() for path in paths}


def entry_names(text: str) -> set[str]:
    """The names a module imports from icpflow.core.errors_and_signals."""
    return {
        alias.name
        for node in ast.walk(ast.parse(text))
        if isinstance(node, ast.ImportFrom) and node.module == "icpflow.core.errors_and_signals"
        for alias in node.names
    }


def test_signal_handlers_are_installed_by_errors_and_signals_only():
    """Every entry point and the training callback install their SIGINT/SIGTERM handlers through
    ``icpflow.core.errors_and_signals.on_signals`` (``stop_on_signals``); the one other call: a labelling worker
    ignoring
    Ctrl-C."""
    calls = []
    for name, text in sources().items():
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ImportFrom) and node.module == "signal":
                calls += [(name, f"from signal import {alias.name}") for alias in node.names]
            elif isinstance(node, ast.Call) and ast.unparse(node.func) == "signal.signal":
                calls.append((name, ast.unparse(node)))
    outside = [call for call in calls if call[0] != "icpflow/core/errors_and_signals.py"]
    assert sorted(outside) == [  # a worker that leaves Ctrl-C to its parent
        ("icpflow/labelling/executors.py", "signal.signal(signal.SIGINT, signal.SIG_IGN)"),
    ]
    assert any(name == "icpflow/core/errors_and_signals.py" for name, _ in calls)  # the check reads the calls


def test_every_entry_point_stops_and_reports_through_errors_and_signals():
    texts = sources()
    # the scripts call the console scripts' mains: Hydra inside errors_and_signals.run (icpflow.core.entry_points), each
    # task's body inside errors_and_signals.reported
    for script in SCRIPTS:
        assert re.search(r"^from (icpflow|fastflow3d)\.[\w.]+ import \w*main$", texts[script], re.M), script
    assert "run" in entry_names(texts["icpflow/core/entry_points.py"])
    for module in ("icpflow/labelling/cli.py", "icpflow/evaluation/cli.py", "fastflow3d/training/cli.py"):
        assert "reported" in entry_names(texts[module]) and "hydra_entry(" in texts[module], module
    assert {"exit_status", "stop_on_signals"} <= entry_names(texts["fastflow3d/inference/cli.py"])
    assert "exit_status" in entry_names(texts["fastflow3d/artifact/export.py"])  # run_export, export.py's body
    for module in ("icpflow/labelling/cli.py", "icpflow/evaluation/cli.py", "fastflow3d/training/trainer.py"):
        assert "stop_on_signals" in entry_names(texts[module]), module
    assert "on_signals" in entry_names(texts["fastflow3d/training/callbacks.py"])


def test_messages_are_folded_onto_one_line_by_errors_and_signals_only():
    folded = re.compile(r"""(['"]) \1\.join\(str\(""")
    found = [name for name, text in sources().items() if folded.search(text)]
    assert found == ["icpflow/core/errors_and_signals.py"]  # one_line itself


def test_importing_errors_and_signals_stays_cheap():
    """Every module may import icpflow.core.errors_and_signals (it imports nothing of the packages but
    icpflow.core.settings and icpflow.core.stops; settings imports only stops, stops none): no heavy library comes
    with it."""
    code = (
        "import sys, icpflow.core.errors_and_signals; print(' '.join(sorted(m for m in sys.modules if '.' not in m)))"
    )
    loaded = set(subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True).stdout.split())
    assert "icpflow" in loaded and not loaded & {"torch", "lightning", "hydra", "omegaconf", "numba", "scipy"}
    assert "icpflow.core.errors_and_signals" in import_graph() and import_graph()[
        "icpflow.core.errors_and_signals"
    ] <= {"icpflow.core.settings", "icpflow.core.stops"}
    assert import_graph()["icpflow.core.settings"] <= {"icpflow.core.stops"}
    assert not import_graph()["icpflow.core.stops"]


#: what a broad handler catches, by name: a stop that arrived inside compiled code is an ImportError or a SystemError
BROAD = {"Exception", "BaseException", "ImportError", "SystemError"}


def broad_handlers(text: str) -> list[ast.ExceptHandler]:
    """The ``except`` clauses of ``text`` that catch :data:`BROAD` (alone or in a tuple), or everything."""
    found = []
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.ExceptHandler):
            kinds = node.type.elts if isinstance(node.type, ast.Tuple) else [node.type]
            if node.type is None or any(ast.unparse(kind).split(".")[-1] in BROAD for kind in kinds):
                found.append(node)
    return found


def lets_a_stop_through(handler: ast.ExceptHandler) -> bool:
    """The handler's first statement is ``raise_stop_behind(<its name>)``, or its last a bare ``raise``."""
    first, last = handler.body[0], handler.body[-1]
    if isinstance(last, ast.Raise) and last.exc is None:
        return True
    return handler.name is not None and ast.unparse(first) == f"raise_stop_behind({handler.name})"


def test_every_broad_handler_lets_a_stop_through():
    """A Ctrl-C or SIGTERM whose handler ran inside compiled code arrives as an ImportError (a compiled module's
    import printed it) or a SystemError (a kernel returned over it): every ``except Exception``, ``except
    ImportError`` (an optional package's fallback) and ``except SystemError`` of the packages raises the stop behind
    the error first (``icpflow.core.stops.raise_stop_behind``), or re-raises, so that no stop is skipped as a bad
    sample, a damaged file or a missing package. The reporter that reads them (``errors_and_signals``) is the one
    exception."""
    missing = [
        f"{name}:{handler.lineno}"
        for name, text in sources().items()
        if name != "icpflow/core/errors_and_signals.py"
        for handler in broad_handlers(text)
        if not lets_a_stop_through(handler)
    ]
    assert missing == []
    # the check reads the handlers: one that swallows is found, one that lets the stop through is not
    swallowing = "try:\n    import x\nexcept (OSError, ImportError):\n    pass\n"
    through = "try:\n    import x\nexcept ImportError as error:\n    raise_stop_behind(error)\n    pass\n"
    assert [lets_a_stop_through(h) for h in broad_handlers(swallowing + through)] == [False, True]
    assert sum(len(broad_handlers(text)) for text in sources().values()) > 20
