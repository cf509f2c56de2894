"""``benchmarks/`` is a package run as ``python -m benchmarks.<script>``: no script puts a folder on Python's path,
the project's packages never import it, and ``benchmarks/README.md`` names every module it holds."""

import ast
import re

from helpers.data import REPO

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


def test_a_benchmarks_cpu_names_the_host_family_model_and_vector_width(monkeypatch):
    # "AMD EPYC" alone named hosts two times apart in speed: the tables name the family, model and vector width,
    # the instruction sets of reduced precisions and the switches that hold the engines below them
    from benchmarks.common import cpu_name

    for name in ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY", "MKL_ENABLE_INSTRUCTIONS", "NUMBA_CPU_NAME"):
        monkeypatch.delenv(name, raising=False)
    first = "processor : 0\nmodel name : AMD EPYC\ncpu family : 26\nmodel : 2\nflags : fpu avx2 avx512f avx512_vnni\n"
    other = "processor : 1\nmodel name : Other\ncpu family : 25\nmodel : 1\nflags : fpu\n"
    vnni = "AMD EPYC (family 26 model 2, AVX-512 VNNI; instruction sets: AVX2, AVX-512, VNNI)"
    assert cpu_name(f"{first}\n{other}") == vnni
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    assert cpu_name(first.replace(" avx512_vnni", "")) == (
        "AMD EPYC (family 26 model 2, AVX-512; instruction sets: AVX2, AVX-512; held by ONEDNN_MAX_CPU_ISA=AVX2)"
    )
    held = "held by ONEDNN_MAX_CPU_ISA=AVX2"
    assert cpu_name(other) == f"Other (family 25 model 1, no AVX2; instruction sets: no AVX2; {held})"
    assert cpu_name("model name : Apple M2\n") == "Apple M2"  # no family (not an x86 Linux): the name alone
