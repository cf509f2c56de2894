"""The docs against the code: what README.md, ARCHITECTURE.md and docs/*.md name exists.

- **Module paths**: every backticked dotted path starting with ``icpflow.`` or ``fastflow3d.``
  (``fastflow3d.inference.refine``, ``icpflow.teacher.config.ICPFlowConfig``, ``icpflow.labelling.options.register()``),
  and every name a fenced example imports from them (``from fastflow3d.inference.predictor import Predictor``),
  resolves: its longest module prefix is found (a file of the repository, else ``importlib.util.find_spec``) and the
  rest are attributes, read from the module's source with ``ast`` where they are defined there (no heavy imports),
  else from the imported module. ``icpflow.<block>.<field>`` and the teacher's older flat names
  (``icpflow.min_cluster_size``) are Hydra keys of the ``icpflow`` group: they resolve against its schema
  (``icpflow.teacher.config.schema``). A name ending in a file suffix (``fastflow3d.onnx``) is a file name. An old
  path kept importable for a release (a shim calling ``icpflow.core.deprecation.warn_moved``, or a name a package
  answers with ``moved_attribute``) fails too, naming today's: the docs name today's paths (a page that means the old
  one, e.g. a list of what moved, says so in ``ALLOWED``).
- **File paths**: every backticked path of the repository's own tree (its first folder one of ``ROOTS``:
  ``fastflow3d/network/cells.py``, ``conf/experiment/synthetic_cpu.yaml``, ``benchmarks/as_avx2.py``) exists;
  ``{a,b}`` is expanded, ``*`` and ``<placeholder>`` match anything (at least one file must match).
- **Commands**: in fenced code blocks and in backticked commands, every config group option ``group=name`` of a
  ``label.py``/``train.py``/``eval.py``/``export.py`` command (``experiment=synthetic_cpu``, ``dataset=kitti``,
  ``hydra/launcher=slurm_ddp``; alternatives ``optim=adam|adamw`` each) is ``conf/<group>/<name>.yaml``, every
  ``python -m benchmarks.X`` / ``fastflow3d.X`` / ``icpflow.X`` names a module of the tree, and every
  ``fastflow3d-*`` / ``icpflow-*`` command is a console script of ``pyproject.toml``.
- **Links**: every relative markdown link of every .md file of the tree (``docs/history.md`` and BENCHMARKS.md
  included: links must keep working whatever the page's age) points to an existing file, and its ``#anchor``, for a
  .md file, to a heading of it (GitHub's rule: lowercase, punctuation but ``-`` and ``_`` dropped, each space a
  ``-``, ``-1``, ``-2`` ... after repeated headings).
- **History headings**: no heading of docs/history.md says ``(in progress)`` but an open issue's (``OPEN_ISSUES``:
  when an issue closes, take it out and give its headings their final state, e.g. ``(resolved in ...)``).

Which pages: the name checks read README.md, ARCHITECTURE.md and docs/*.md but ``docs/history.md``, which records
each issue as it was (scripts, modules and options under the names they had then, since renamed or removed); and
not BENCHMARKS.md, whose rows keep each figure's command as it ran at the row's commit (retired scripts included,
said so). A name a checked page means as an old or removed one is allowed in ``ALLOWED`` with the reason.

Each failure names the file, the line and the missing thing. The whole file runs in about a second.
"""

import ast
import functools
import glob
import importlib
import importlib.util
import re
import shlex
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

from helpers.data import REPO

PACKAGES = ("icpflow", "fastflow3d")
#: the pages whose names of modules, files, options and commands are checked
NAMED_PAGES = ("README.md", "ARCHITECTURE.md", *sorted(f"docs/{p.name}" for p in (REPO / "docs").glob("*.md")))
NAMED_PAGES = tuple(page for page in NAMED_PAGES if page != "docs/history.md")
#: every page whose links are checked
LINKED_PAGES = tuple(
    sorted(str(p.relative_to(REPO)) for pattern in ("*.md", "docs/*.md", "benchmarks/*.md") for p in REPO.glob(pattern))
)
#: a backticked path starting with one of these folders is a path of the repository's tree
ROOTS = ("icpflow", "fastflow3d", "conf", "benchmarks", "tests", "docs", ".ci")
#: the issues still open: only their headings in docs/history.md may say "(in progress)"
OPEN_ISSUES = frozenset({65})
ENTRY_SCRIPTS = ("label.py", "train.py", "eval.py", "export.py")
FILE_SUFFIXES = ("onnx", "pt2", "pt", "ckpt", "json", "jsonl", "yaml", "py", "md", "h5", "npz", "npy", "bin", "rrd")
#: names the checked pages use on purpose although they do not exist (as written, the reason)
ALLOWED = {
    "icpflow/schema": "a Hydra ConfigStore entry (icpflow.teacher.config.register_configs), not a file",
    "hydra/launcher=submitit_slurm": "the hydra-submitit-launcher plugin's own config, not one of conf/",
}


@dataclass(frozen=True)
class Span:
    page: str
    line: int
    text: str
    fenced: bool  # a line of a fenced code block (else an inline code span)


@dataclass(frozen=True)
class Page:
    path: str
    lines: tuple[str, ...]
    fenced: frozenset[int]  # 0-based indices of the lines inside fenced blocks (fences included)

    def prose(self):
        """(first line index, text) of each paragraph outside fenced blocks."""
        block, start = [], None
        for i, line in enumerate(self.lines):
            if i in self.fenced or not line.strip():
                if block:
                    yield start, "\n".join(block)
                block, start = [], None
                continue
            if start is None:
                start = i
            block.append(line)
        if block:
            yield start, "\n".join(block)


@functools.cache
def page(path: str) -> Page:
    lines = (REPO / path).read_text(encoding="utf-8").splitlines()
    fenced, inside = set(), False
    for i, line in enumerate(lines):
        if line.lstrip().startswith("```"):
            fenced.add(i)
            inside = not inside
        elif inside:
            fenced.add(i)
    return Page(path, tuple(lines), frozenset(fenced))


CODE_SPAN = re.compile(r"(?<!`)(`+)(?!`)(.+?)(?<!`)\1(?!`)", re.S)


@functools.cache
def spans(path: str) -> tuple[Span, ...]:
    """Inline code spans (across line breaks, ``\\|`` read as ``|``) and fenced lines (a command continued with
    a trailing backslash joined into one) of a page."""
    p, found = page(path), []
    for start, text in p.prose():
        for match in CODE_SPAN.finditer(text):
            line = start + 1 + text.count("\n", 0, match.start(2))
            found.append(Span(path, line, " ".join(match.group(2).replace("\\|", "|").split()), False))
    joined, first = "", None
    for i, line in enumerate(p.lines):
        if i not in p.fenced or line.lstrip().startswith("```"):
            continue
        first = i if first is None else first
        if line.rstrip().endswith("\\"):
            joined += line.rstrip()[:-1] + " "
            continue
        found.append(Span(path, first + 1, joined + line, True))
        joined, first = "", None
    return tuple(found)


# --------------------------------------------------------------------------------------------- module paths


def module_file(name: str) -> Path | None:
    """The source of a module of the tree (``a.b`` -> ``a/b.py`` or ``a/b/__init__.py``), without importing it."""
    base = REPO.joinpath(*name.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def module_exists(name: str) -> bool:
    if module_file(name):
        return True
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def _definitions(body) -> dict[str, ast.AST]:
    """The names a module or class body binds (functions, classes, assignments, imports; inside ``if``/``try``
    too), each with the node that binds it; ``*`` when it star-imports or defines ``__getattr__``."""
    names = {}
    for node in body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names[node.name] = node
        elif isinstance(node, ast.Assign):
            for target in node.targets:
                for leaf in ast.walk(target):
                    if isinstance(leaf, ast.Name):
                        names[leaf.id] = node
        elif isinstance(node, (ast.AnnAssign, ast.AugAssign)) and isinstance(node.target, ast.Name):
            names[node.target.id] = node
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            for alias in node.names:
                names[alias.asname or alias.name.split(".")[0]] = node
        elif isinstance(node, (ast.If, ast.Try, ast.With)):
            for part in ("body", "orelse", "finalbody"):
                names.update(_definitions(getattr(node, part, [])))
            for handler in getattr(node, "handlers", []):
                names.update(_definitions(handler.body))
    if "__getattr__" in names or any(
        isinstance(n, ast.ImportFrom) and any(a.name == "*" for a in n.names) for n in body
    ):
        names["*"] = None
    return names


def _class_members(node: ast.ClassDef) -> dict[str, ast.AST]:
    members = _definitions(node.body)
    for leaf in ast.walk(node):  # instance attributes: self.x = ...
        if isinstance(leaf, ast.Attribute) and isinstance(leaf.ctx, ast.Store):
            if isinstance(leaf.value, ast.Name) and leaf.value.id == "self":
                members.setdefault(leaf.attr, leaf)
    return members


@functools.cache
def _module_tree(name: str) -> ast.Module | None:
    path = module_file(name)
    return ast.parse(path.read_text(encoding="utf-8"), str(path)) if path else None


def _lazy_export(tree: ast.Module, name: str) -> bool:
    """Whether a module's ``__getattr__`` answers ``name`` by its own text (``if name in ("ICPFlow", ...)``), not
    as a moved old name (``moved_attribute``)."""
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and node.name == "__getattr__":
            inside = list(ast.walk(node))
            if any(isinstance(n, ast.Name) and n.id == "moved_attribute" for n in inside):
                return False
            return any(isinstance(n, ast.Constant) and n.value == name for n in inside)
    return False


def _static_attribute(module: str, attrs: list[str]) -> bool | None:
    """True / False where the module's source says; None where only importing it can tell."""
    tree = _module_tree(module)
    if tree is None:
        return None
    names = _definitions(tree.body)
    node = names.get(attrs[0])
    if node is None:
        if len(attrs) == 1 and _lazy_export(tree, attrs[0]):
            return True
        return None if "*" in names else False
    if len(attrs) == 1:
        return True
    if isinstance(node, ast.ClassDef):
        members = _class_members(node)
        if attrs[1] in members:
            inner = members[attrs[1]]
            if len(attrs) == 2:
                return True
            if isinstance(inner, ast.ClassDef):
                return _static_attribute_of_class(inner, attrs[2:])
        return None  # inherited, or set elsewhere
    if isinstance(node, ast.ImportFrom) and node.level == 0:
        source = next(a.name for a in node.names if (a.asname or a.name) == attrs[0])
        return resolve(".".join([node.module, source, *attrs[1:]])) is None
    return None


def _static_attribute_of_class(node: ast.ClassDef, attrs: list[str]) -> bool | None:
    members = _class_members(node)
    if attrs[0] not in members:
        return None
    if len(attrs) == 1:
        return True
    inner = members[attrs[0]]
    return _static_attribute_of_class(inner, attrs[1:]) if isinstance(inner, ast.ClassDef) else None


def shim_of(module: str) -> str | None:
    """Today's path where ``module`` is a deprecated shim of an old path (its body calls ``warn_moved``)."""
    tree = _module_tree(module)
    for node in tree.body if tree else ():
        call = node.value if isinstance(node, (ast.Expr, ast.Assign)) else None
        if isinstance(call, ast.Call) and getattr(call.func, "id", getattr(call.func, "attr", "")) == "warn_moved":
            return ast.literal_eval(call.args[1]) if len(call.args) > 1 else "(see the module)"
    return None


MOVED = " is deprecated and will be removed in "  # icpflow.core.deprecation's words


def resolve(dotted: str) -> str | None:
    """None where ``dotted`` is a module or a module's attribute of today's code, else what is missing (or that it
    is a deprecated old path)."""
    parts = dotted.split(".")
    k = next((k for k in range(len(parts), 0, -1) if module_exists(".".join(parts[:k]))), 0)
    if k == 0:
        return f"no module {parts[0]}"
    for j in range(2, k + 1):
        new = shim_of(".".join(parts[:j]))
        if new:
            return f"{'.'.join(parts[:j])} is a deprecated old path (a shim): today {new}"
    module, attrs = ".".join(parts[:k]), parts[k:]
    if not attrs:
        return None
    known = _static_attribute(module, attrs)
    if known is None:  # only the imported module can say
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                value = importlib.import_module(module)
                for attr in attrs:
                    value = getattr(value, attr)
                known = True
            except (ImportError, AttributeError):
                known = False
        moved = [str(w.message) for w in caught if MOVED in str(w.message)]
        if known and moved:
            return f"a deprecated old path: {moved[-1]}"
    return None if known else f"module {module} has no {'.'.join(attrs)}"


@functools.cache
def teacher_keys() -> frozenset[str]:
    """The Hydra keys of the ``icpflow`` group: its fields, each block's fields (``block.field``), the older flat
    names."""
    import dataclasses

    from icpflow.teacher import config

    keys = {f.name for f in dataclasses.fields(config.schema())}
    for block, kind in config.BLOCKS.items():
        keys.update(f"{block}.{f.name}" for f in dataclasses.fields(kind))
    return frozenset(keys)


DOTTED = re.compile(r"(?<![\w./-])((?:icpflow|fastflow3d)(?:\.\s?[A-Za-z_]\w*)+)(\(.*?\))?(=?)")


def dotted_names(span: Span):
    """(name, is a Hydra override key) of each dotted package path in a span."""
    for match in DOTTED.finditer(span.text):
        name = re.sub(r"\.\s", ".", match.group(1))
        if name.rsplit(".", 1)[1] in FILE_SUFFIXES:
            continue
        yield name, bool(match.group(3))


IMPORT = re.compile(
    r"^\s*(?:from\s+((?:icpflow|fastflow3d)[\w.]*)\s+import\s+(.+?)|import\s+((?:icpflow|fastflow3d)[\w.]*).*)$"
)


def imported_names(span: Span):
    """(name, False) of what a fenced example's ``from icpflow... import a, b`` / ``import fastflow3d...`` takes."""
    match = IMPORT.match(span.text.split("#")[0])
    if not match:
        return
    if match.group(3):
        yield match.group(3), False
        return
    for alias in match.group(2).strip("() ").split(","):
        if alias.strip():
            yield f"{match.group(1)}.{alias.split()[0]}", False


def test_module_paths_resolve():
    problems = []
    for path in NAMED_PAGES:
        for span in spans(path):
            for name, is_key in imported_names(span) if span.fenced else dotted_names(span):
                if name in ALLOWED:
                    continue
                if name.startswith("icpflow.") and name.removeprefix("icpflow.") in teacher_keys():
                    continue  # a Hydra key of the icpflow group
                missing = (
                    f"no Hydra key {name} in the icpflow group (icpflow.teacher.config.schema)"
                    if is_key
                    else resolve(name)
                )
                if missing:
                    problems.append(f"{path}:{span.line}: `{name}`: {missing}")
    assert not problems, "backticked module paths that do not resolve:\n" + "\n".join(problems)


# --------------------------------------------------------------------------------------------- file paths


PATH_TOKEN = re.compile(r"^(?:\./)?((?:" + "|".join(map(re.escape, ROOTS)) + r")/(?:\{[^{}\s]*\}|[^\s`'\"(),;:{])*)")


def _expand(path: str) -> list[str]:
    match = re.search(r"\{([^{}]*)\}", path)
    if not match:
        return [path]
    return [
        x for option in match.group(1).split(",") for x in _expand(path[: match.start()] + option + path[match.end() :])
    ]


def path_tokens(span: Span):
    for token in span.text.split():
        token = token.split("=", 1)[1] if "=" in token and not token.startswith(ROOTS) else token
        match = PATH_TOKEN.match(token.strip("'\"[]"))
        if match:
            path = match.group(1).rstrip(".")
            if "..." in path or "$" in path:
                continue
            yield path


def path_missing(path: str) -> bool:
    for option in _expand(path):
        pattern = re.sub(r"<[^>]*>", "*", option)
        if not (glob.glob(str(REPO / pattern)) if "*" in pattern else (REPO / pattern).exists()):
            return True
    return False


def test_file_paths_exist():
    problems = []
    for path in NAMED_PAGES:
        for span in spans(path):
            if span.fenced:
                continue
            for name in path_tokens(span):
                if name in ALLOWED:
                    continue
                if path_missing(name):
                    problems.append(f"{path}:{span.line}: `{name}`: no such file or folder in the repository")
                elif name.endswith(".py") and name.startswith(PACKAGES) and shim_of(name[:-3].replace("/", ".")):
                    new = shim_of(name[:-3].replace("/", "."))
                    problems.append(f"{path}:{span.line}: `{name}`: a deprecated old module (a shim): today {new}")
    assert not problems, "backticked paths that do not exist:\n" + "\n".join(problems)


# --------------------------------------------------------------------------------------------- commands


def _words(command: str) -> list[str]:
    command = re.sub(r"(^|\s)#(?!SBATCH).*$", "", command)  # a comment
    try:
        return shlex.split(command)
    except ValueError:
        return command.split()


def _commands(span: Span):
    """Each command of a span (split at ``&&``, ``;``, ``|`` outside words), as its words."""
    for part in re.split(r"&&|;|\s\|\s", span.text):
        words = _words(part)
        if words:
            yield words


@functools.cache
def config_groups() -> frozenset[str]:
    conf = REPO / "conf"
    return frozenset(str(d.relative_to(conf)) for d in conf.rglob("*") if d.is_dir())


def group_options(span: Span):
    """(``group=option`` as written, group, option) of each config group option of an entry script's command,
    or of a span made of ``group=option`` words alone."""
    for words in _commands(span):
        script = next((i for i, w in enumerate(words) if Path(w).name in ENTRY_SCRIPTS), None)
        if script is None and not all("=" in w for w in words):
            continue
        for word in words[(script or -1) + 1 :]:
            key, eq, value = word.lstrip("+~").partition("=")
            if not eq or key not in config_groups() or not value or re.search(r"[<>$.{}]", value):
                continue
            for option in re.split(r"[|,]", value):
                yield f"{key}={option}", key, option


def module_commands(span: Span):
    for match in re.finditer(r"python[\w.]*\s+-m\s+([\w.]*\w)(?![\w.<])", span.text):  # not X.<script>
        if match.group(1).split(".")[0] in ("benchmarks", *PACKAGES):
            yield match.group(1)


@functools.cache
def console_scripts() -> frozenset[str]:
    """The names of ``[project.scripts]`` (read as text: ``tomllib`` is Python 3.11's, the package runs on 3.10)."""
    text = (REPO / "pyproject.toml").read_text(encoding="utf-8")
    section = re.search(r"^\[project\.scripts\]\s*$(.*?)(?=^\[|\Z)", text, re.M | re.S)
    return frozenset(re.findall(r'^\s*"?([\w.-]+)"?\s*=', section.group(1), re.M) if section else ())


def script_commands(span: Span):
    """The ``fastflow3d-*`` / ``icpflow-*`` commands a span runs (a word alone, like a method name, is no
    command)."""
    for words in _commands(span):
        for i, word in enumerate(words):
            name = Path(word).name
            if re.fullmatch(r"(?:fastflow3d|icpflow)-[a-z][a-z0-9-]*", name) and (span.fenced or len(words) > 1):
                if i == 0 or words[i - 1] in ("sudo", "exec", "srun", "time"):
                    yield name


def test_commands_name_what_exists():
    problems = []
    for path in NAMED_PAGES:
        for span in spans(path):
            for written, group, option in group_options(span):
                if written not in ALLOWED and not (REPO / "conf" / group / f"{option}.yaml").is_file():
                    problems.append(f"{path}:{span.line}: `{written}`: no conf/{group}/{option}.yaml")
            for module in module_commands(span):
                if not module_exists(module):
                    problems.append(f"{path}:{span.line}: `python -m {module}`: no module {module}")
                elif shim_of(module) and module not in ALLOWED:
                    problems.append(f"{path}:{span.line}: `python -m {module}`: a deprecated shim of {shim_of(module)}")
            for name in script_commands(span):
                if name not in console_scripts():
                    problems.append(f"{path}:{span.line}: `{name}`: not a console script of pyproject.toml")
    assert not problems, "commands naming what does not exist:\n" + "\n".join(problems)


# --------------------------------------------------------------------------------------------- links


def slug(heading: str) -> str:
    """GitHub's anchor of a heading's text."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link: its text
    text = re.sub(r"[^\w\- ]", "", text.strip().lower())
    return text.replace(" ", "-")


@functools.cache
def anchors(path: str) -> frozenset[str]:
    p, counts, found = page(path), {}, set()
    for i, line in enumerate(p.lines):
        match = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if match and i not in p.fenced:
            base = slug(match.group(1))
            n = counts.get(base, 0)
            found.add(f"{base}-{n}" if n else base)  # a repeated heading: -1, -2, ...
            counts[base] = n + 1
    return frozenset(found)


LINK = re.compile(r"(?<!!)\[(?:[^\[\]]|\[[^\]]*\])*\]\(([^()\s]+)\)")


def test_links_and_anchors():
    problems = []
    for path in LINKED_PAGES:
        p = page(path)
        for start, text in p.prose():
            prose = CODE_SPAN.sub(lambda m: re.sub(r"[^\n]", "`", m.group(0)), text)  # no link inside code
            for match in LINK.finditer(prose):
                target = match.group(1)
                line = start + 1 + text.count("\n", 0, match.start())
                if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto:
                    continue
                file, _, anchor = target.partition("#")
                where = (REPO / path).parent / file if file else REPO / path
                shown = file or path
                if not where.exists():
                    problems.append(f"{path}:{line}: link ({target}): no file {shown}")
                elif anchor and where.suffix == ".md":
                    linked = str(where.resolve().relative_to(REPO))
                    if anchor not in anchors(linked):
                        problems.append(f"{path}:{line}: link ({target}): no heading #{anchor} in {linked}")
    assert not problems, "links to a file or heading that does not exist:\n" + "\n".join(problems)


def test_slug_follows_github():
    assert slug("Issue 33, 2026-11-27 (later): ONNX Runtime's pillar scatters") == (
        "issue-33-2026-11-27-later-onnx-runtimes-pillar-scatters"
    )
    assert slug("Issue 43, fourth session: `synthetic_cpu` on 1,024 pairs") == (
        "issue-43-fourth-session-synthetic_cpu-on-1024-pairs"
    )
    assert slug("Training: `train.py`") == "training-trainpy"


# --------------------------------------------------------------------------------------------- history


def test_history_headings_give_their_final_state():
    problems = []
    for i, line in enumerate(page("docs/history.md").lines):
        if line.startswith("#") and "in progress" in line.lower():
            issue = re.match(r"^#+\s+Issue (\d+)", line)
            if not issue or int(issue.group(1)) not in OPEN_ISSUES:
                problems.append(f"docs/history.md:{i + 1}: {line.strip()}")
    assert not problems, (
        "headings still '(in progress)' of issues that are not open (OPEN_ISSUES): give each its final state, "
        "e.g. '(resolved in the thirteenth session)', and update the links to it:\n" + "\n".join(problems)
    )


if __name__ == "__main__":  # pragma: no cover
    sys.exit(__import__("pytest").main([__file__, "-q"]))


def test_the_packages_cite_no_issue_numbers_of_ours():
    """Comments say why in the present: the history of a choice (which issue, which session, before -> after) lives
    in BENCHMARKS.md and docs/history.md. Another project's tracker (``onnxruntime's GitHub issue 18048``) is a
    reference, not history."""
    ours = re.compile(r"(?<!GitHub )\bissues? \d+", re.IGNORECASE)
    found = [
        f"{path.relative_to(REPO)}:{number}"
        for package in ("icpflow", "fastflow3d")
        for path in sorted((REPO / package).rglob("*.py"))
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if ours.search(line)
    ]
    assert found == []
    assert ours.search("# issue 44: faster") and not ours.search("onnxruntime's GitHub issue 18048")
