"""A first run that explains itself: the teacher's numba kernels are cached on disk and compiled once, with a line
saying so (icpflow.teacher.warmup); a dataset with no samples for a horizon says why (the shipped AV2 log and
KITTI scans)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from icpflow.datasets.from_config import DatasetError, open_dataset
from icpflow.teacher import warmup

from helpers.data import REPO, needs_shared, shared

AV2_LOG = "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"


def test_every_kernel_is_cached_on_disk():
    kernels = warmup.kernels()
    # the teacher's kernels: nearest neighbours, ICP, histogram vote, batch registration
    expected = {
        "scans.neighbours.nearest",
        "teacher.registration.icp.icp_point_to_plane",
        "teacher.histogram._scores",
        "teacher.registration.cpu._register_batch",
    }
    assert expected <= set(kernels)
    not_cached = [name for name, kernel in kernels.items() if not kernel._cache.__class__.__name__ == "FunctionCache"]
    assert not not_cached, f"kernels without cache=True compile in every process: {not_cached}"


def test_every_kernel_releases_the_gil():
    """An overlapped stream runs the ground and the odometry on its own thread and the refinement in its worker: a
    kernel that held the GIL stopped the other thread's Python for its whole run (numba's default)."""
    import numba

    kernels = warmup.kernels()
    assert {
        "scans.ground._ground_height",
        "scans.neighbours.k_nearest",
        "teacher.registration.cpu._register_stages_batch",
    } <= set(kernels)
    holding = [name for name, kernel in kernels.items() if not kernel.targetoptions.get("nogil")]
    assert not holding and all(isinstance(kernel, numba.core.registry.CPUDispatcher) for kernel in kernels.values())


def test_a_fresh_cache_is_seen_as_cold(tmp_path):
    """In a new environment (an empty NUMBA_CACHE_DIR) every kernel is cold; nothing is compiled by the check."""
    code = "import json; from icpflow.teacher import warmup; print(json.dumps(warmup.cold_kernels()))"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert sorted(json.loads(done.stdout)) == sorted(warmup.kernels())
    assert not list(tmp_path.rglob("*.nbc"))  # no machine code written: the check compiled nothing


def test_the_warmup_reaches_the_refinements_kernels():
    """``compile_kernels`` (setup.sh's warm-up) calls the kernels of ``KERNEL_MODULES`` that the teacher's pair
    never reaches, the student refinement's batch ICP, nearest distances and bird's-eye-view cells
    (``fastflow3d.inference.refine``): left out, they stayed cold after set-up, and every label.py or eval.py run said
    it compiled the kernels again (a first label test of a fresh clone caught it). In a fresh process, so that no
    other test has called them."""
    refinements = (
        "teacher.registration.cpu._register_stages_batch",
        "scans.neighbours.nearest_distances",
        "scans.bev.occupied_cells",
        "scans.bev.in_box_cells",
    )
    code = (
        "from icpflow.teacher import warmup; warmup.compile_kernels(); kernels = warmup.kernels(); "
        f"print(sorted(name for name in {refinements!r} if not kernels[name].signatures))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=600)
    assert done.stdout.strip().splitlines()[-1] == "[]"


def test_ensure_compiled_says_what_it_does(monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(warmup, "compile_kernels", lambda: calls.append(1))
    monkeypatch.setattr(
        warmup,
        "cold_kernels",
        lambda stale=None: ["teacher.registration.icp.icp_point_to_point", "teacher.histogram._scores"],
    )
    monkeypatch.setattr(warmup, "stale_cache", lambda: False)  # nothing of the real cache is emptied or stamped
    assert warmup.ensure_compiled("label") is True and calls == [1]
    lines = capsys.readouterr().err.splitlines()
    assert lines[0].startswith("label: compiling the teacher's 2 numba kernels once for this environment (about")
    assert lines[1].startswith("label: kernels compiled in ")
    # a cache of other sources: emptied (each kernel's index), compiled, stamped, and the line says why
    flushed, stamped = [], []

    class Cache:
        def flush(self):
            flushed.append(1)

    class Kernel:
        _cache = Cache()

    monkeypatch.setattr(warmup, "stale_cache", lambda: True)
    monkeypatch.setattr(warmup, "kernels", lambda: {"k": Kernel()})
    monkeypatch.setattr(warmup, "_cache_folder", lambda: Path("cache"))
    monkeypatch.setattr(warmup, "write_text_atomic", lambda path, text, **_: stamped.append((path, text)))
    monkeypatch.setattr(warmup, "sources_fingerprint", lambda: "f")
    assert warmup.ensure_compiled("infer") is True and calls == [1, 1] and flushed == [1]
    assert stamped == [(Path("cache") / warmup.SOURCES_STAMP, "f")]
    assert "once for this environment and these sources (about" in capsys.readouterr().err.splitlines()[0]
    monkeypatch.setattr(warmup, "cold_kernels", lambda stale=None: [])
    assert warmup.ensure_compiled("label") is False and calls == [1, 1]
    assert capsys.readouterr().err == ""  # a warm cache: not a word


def test_a_lazy_check_empties_a_stale_cache_and_compiles_nothing(monkeypatch, capsys):
    """``eager=False`` (the Predictor): a cache of other sources is emptied and stamped with one line, nothing is
    compiled; a cache of these sources, however cold, is left to compile each kernel on its first call, silently."""
    calls, restarted = [], []
    monkeypatch.setattr(warmup, "compile_kernels", lambda: calls.append(1))
    monkeypatch.setattr(warmup, "_restart_cache", lambda: restarted.append(1))
    monkeypatch.setattr(warmup, "cold_kernels", lambda stale=None: ["teacher.registration.icp.icp_point_to_point"])
    monkeypatch.setattr(warmup, "stale_cache", lambda: True)
    assert warmup.ensure_compiled("fastflow3d", eager=False) is True and restarted == [1] and calls == []
    assert capsys.readouterr().err.startswith("fastflow3d: the numba kernels it calls compile on their first call")
    monkeypatch.setattr(warmup, "stale_cache", lambda: False)
    assert warmup.ensure_compiled("fastflow3d", eager=False) is False and restarted == [1] and calls == []
    assert capsys.readouterr().err == ""


def _label_cfg(*overrides):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose("label", list(overrides))


@needs_shared("av2", "sensor", "val", AV2_LOG, what="the real Argoverse 2 log")
def test_av2_log_too_short_for_the_horizon_says_so():
    pytest.importorskip("av2", reason="the av2 package is an optional dependency (pip install icpflow[av2])")
    cfg = _label_cfg("dataset=av2", f"dataset.root={shared('av2')}", "split=val")
    assert len(open_dataset(cfg, 1)) == 1
    with pytest.raises(DatasetError) as error:
        open_dataset(cfg, 2)
    assert str(error.value) == (
        f"dataset av2: no samples under {shared('av2').resolve()} (split val): log {AV2_LOG} has 2 sweeps: "
        "a pair 2 apart needs at least 3 (horizon=2)"
    )


@needs_shared("kitti_hdl64_scans", what="the real KITTI HDL-64 scans")
def test_kitti_scans_too_few_for_the_horizon_say_so():
    root = shared("kitti_hdl64_scans")
    count = len(list(root.glob("*.bin")))
    cfg = _label_cfg("dataset=kitti", f"dataset.root={root}")
    assert len(open_dataset(cfg, count - 1)) == 1
    with pytest.raises(DatasetError, match=rf"sequence kitti_hdl64_scans has {count} scans: a pair {count} apart"):
        open_dataset(cfg, count)


def test_a_kernel_never_runs_the_old_code_of_another_modules_kernel_it_calls(tmp_path):
    """numba keys a kernel's cache by its own file: a caller cached with a callee of another module kept the old
    callee after that file changed (g = 10 f(x): 20 where the new f gives 30). ``ensure_compiled`` sees the sources
    changed (the cache's stamp) and compiles everything afresh."""
    package = tmp_path / "pk"
    package.mkdir()
    (package / "__init__.py").write_text("")
    callee = "import numba\n\n\n@numba.njit(cache=True)\ndef f(x):\n    return x + {}\n"
    (package / "a.py").write_text(callee.format(1))
    (package / "b.py").write_text(
        "import numba\n\nfrom pk.a import f\n\n\n@numba.njit(cache=True)\ndef g(x):\n    return f(x) * 10\n"
    )
    env = {key: value for key, value in os.environ.items() if key != "NUMBA_CACHE_DIR"}
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), str(REPO)])

    def run(checked: bool) -> str:
        code = "from pk.b import g; print(g(1))"
        if checked:
            code = (
                "from icpflow.teacher import warmup; warmup.KERNEL_MODULES = ('pk.a', 'pk.b'); "
                "warmup.compile_kernels = lambda: __import__('pk.b').b.g(1); warmup.ensure_compiled('t'); " + code
            )
        done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        return done.stdout.split()[-1]

    assert run(checked=True) == "20"
    assert (package / "__pycache__" / warmup.SOURCES_STAMP).is_file()
    (package / "a.py").write_text(callee.format(20))  # another size: numba sees its own file changed
    assert run(checked=False) == "20"  # numba alone: g's cached code still holds f(x) = x + 1
    assert run(checked=True) == "210"  # the stamp differs: everything compiled afresh, g with the new f
    assert run(checked=False) == "210"  # and cached so


def test_every_module_with_kernels_is_stamped():
    """The cache's stamp covers the sources of ``KERNEL_MODULES``: a kernel in another module would be warmed by no
    one and stamped by nothing (a caller of it could keep its old code)."""
    import ast

    def jitted(path: Path) -> bool:
        functions = [node for node in ast.walk(ast.parse(path.read_text())) if isinstance(node, ast.FunctionDef)]
        decorators = [ast.unparse(decorator) for function in functions for decorator in function.decorator_list]
        return any("jit" in decorator for decorator in decorators)

    defining = {
        ".".join(path.relative_to(REPO).with_suffix("").parts)
        for package in ("icpflow", "fastflow3d")
        for path in (REPO / package).rglob("*.py")
        if jitted(path)
    }
    assert defining == set(warmup.KERNEL_MODULES)
