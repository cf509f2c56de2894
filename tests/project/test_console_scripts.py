"""The entry points as a user of an installed package gets them: the console scripts of the wheel (``icpflow-label``,
``fastflow3d-train``, ``fastflow3d-eval``, ``fastflow3d-export``, ``fastflow3d-infer``) resolve to callables, the
wheel carries every config (``conf/`` as ``icpflow_conf``) and its scripts find them outside any checkout; each Hydra
entry point, run from a folder outside the checkout, answers ``--version`` with ``<prog> <version>`` and ``--help``
with one screen naming its own config groups and options only, whose three examples compose."""

import configparser
import importlib
import os
import re
import runpy
import shlex
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

import icpflow

from helpers.data import REPO

CONF = REPO / "conf"
#: what a wheel is built from (a copy of these, so that the build writes nothing into the checkout)
SOURCES = ("pyproject.toml", "setup.py", "README.md", "LICENSE", "icpflow", "fastflow3d", "conf")
#: console script -> (its primary config, the checkout's script calling the same main)
HYDRA_SCRIPTS = {
    "icpflow-label": ("label", "label.py"),
    "fastflow3d-train": ("train", "train.py"),
    "fastflow3d-eval": ("eval", "eval.py"),
    "fastflow3d-export": ("export", "export.py"),
}
HELP_LINES = 40  # one screen


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel of the checkout as it is (pip, no build isolation: the build tools of this environment)."""
    source, out = tmp_path_factory.mktemp("source"), tmp_path_factory.mktemp("wheel")
    for name in SOURCES:
        path = REPO / name
        if path.is_dir():
            shutil.copytree(path, source / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        elif path.is_file():
            shutil.copy2(path, source / name)
    command = [sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation", "-q"]
    subprocess.run([*command, "-w", str(out)], check=True, capture_output=True, timeout=600)
    (built,) = out.glob("icpflow-*.whl")
    return built


def console_scripts(wheel: Path) -> dict[str, str]:
    """The wheel's console scripts: name -> ``module:function``."""
    with zipfile.ZipFile(wheel) as archive:
        (name,) = [name for name in archive.namelist() if name.endswith(".dist-info/entry_points.txt")]
        parser = configparser.ConfigParser()
        parser.read_string(archive.read(name).decode())
    return dict(parser["console_scripts"])


def resolve(target: str):
    """The callable of an entry point ``module:function``."""
    module, _, function = target.partition(":")
    return getattr(importlib.import_module(module), function)


def wrapper(name: str, target: str) -> list[str]:
    """What console script ``name`` runs, as pip's wrapper does (``sys.argv[0]`` the script's name,
    ``sys.exit(function())``), in this Python."""
    module, _, function = target.partition(":")
    code = f"import sys; from {module} import {function}; sys.argv[0] = {name!r}; sys.exit({function}())"
    return [sys.executable, "-c", code]


def console_command(name: str, target: str, *args: str) -> list[str]:
    """The command line of console script ``name``: the installed script where this environment has it (an install
    since it was added), else :func:`wrapper`."""
    installed = Path(sys.executable).parent / name
    return [str(installed), *args] if installed.is_file() else [*wrapper(name, target), *args]


def hydra_targets() -> dict[str, str]:
    """Console script -> ``module:function`` of the Hydra entry points, as pyproject.toml names them."""
    lines = re.findall(r'^([\w-]+) = "([\w.]+:\w+)"$', (REPO / "pyproject.toml").read_text(), re.M)
    return {name: target for name, target in lines if name in HYDRA_SCRIPTS}


def test_every_console_script_resolves_to_a_callable(wheel):
    scripts = console_scripts(wheel)
    assert set(scripts) == {*HYDRA_SCRIPTS, "fastflow3d-infer"}
    for name, target in scripts.items():
        assert callable(resolve(target)), name
    # the teacher wing's script lives in it; eval adds the student's methods, so it lives in the student's wing
    assert scripts["icpflow-label"].startswith("icpflow.") and scripts["fastflow3d-eval"].startswith("fastflow3d.")


def test_the_wheel_carries_every_config(wheel):
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
    configs = {f"icpflow_conf/{path.relative_to(CONF).as_posix()}" for path in CONF.rglob("*.yaml")}
    assert len(configs) > 40 and {"icpflow_conf/label.yaml", "icpflow_conf/hydra/help/train.yaml"} <= configs
    assert configs | {"icpflow_conf/__init__.py"} <= names, sorted(configs - names)
    assert not [name for name in names if name.startswith(("conf/", "tests/"))]  # no stray top-level folder


def test_the_wheel_carries_the_shipped_model(wheel):
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
    shipped = REPO / "fastflow3d" / "artifact" / "models" / "synthetic_cpu"
    files = {f"fastflow3d/artifact/models/synthetic_cpu/{path.name}" for path in shipped.iterdir()}
    assert {"metadata.json", "MODEL_CARD.md", "fastflow3d.onnx", "fastflow3d.int8.onnx"} == {
        name.rpartition("/")[2] for name in files
    }
    assert files <= names, sorted(files - names)


def test_the_wheels_scripts_find_their_configs_outside_a_checkout(wheel, tmp_path):
    """The wheel unpacked (a pure wheel's files are its installation) before this environment's packages: its
    ``icpflow`` has no ``conf/`` beside it, so the configs come from the package ``icpflow_conf``."""
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as archive:
        archive.extractall(site)
    env = {**os.environ, "PYTHONPATH": str(site)}  # the wheel's packages first, this environment's dependencies
    command = wrapper("icpflow-label", console_scripts(wheel)["icpflow-label"])  # the wheel's, not an installed one
    done = subprocess.run(
        [*command, "--info", "searchpath"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    assert "pkg://icpflow_conf" in done.stdout and str(REPO) not in done.stdout
    done = subprocess.run([*command, "--help"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stdout.startswith("icpflow-label "), done.stderr


# ------------------------------------------------------------------------------------------------------- --version


@pytest.mark.parametrize("name", sorted(HYDRA_SCRIPTS))
def test_version_of_every_console_script(name, monkeypatch, capsys):
    """``<prog> <version>`` before Hydra reads the command line (its own --version prints Hydra's)."""
    target = hydra_targets()[name]
    monkeypatch.setattr(sys, "argv", [f"/somewhere/bin/{name}", "--version"])
    assert resolve(target)() is None
    assert capsys.readouterr().out == f"{name} {icpflow.__version__}\n"
    monkeypatch.setattr(sys, "argv", [name, "split=val", "--version"])  # anywhere on the line
    resolve(target)()
    assert capsys.readouterr().out == f"{name} {icpflow.__version__}\n"


@pytest.mark.parametrize("script", sorted(script for _, script in HYDRA_SCRIPTS.values()))
def test_version_of_every_script_of_the_checkout(script, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", [str(REPO / script), "--version"])
    runpy.run_path(str(REPO / script), run_name="__main__")
    assert capsys.readouterr().out == f"{script} {icpflow.__version__}\n"


# ---------------------------------------------------------------------------------------------------------- --help


def section(text: str, title: str) -> list[str]:
    """The lines of the help ``text`` under the heading line starting with ``title``, up to the next blank line."""
    lines = text.splitlines()
    starts = [index for index, line in enumerate(lines) if line.startswith(title)]
    if not starts:
        return []
    body = []
    for line in lines[starts[0] + 1 :]:
        if not line.strip():
            break
        body.append(line)
    return body


def has_key(cfg, dotted: str) -> bool:
    """Whether the composed config has the option ``dotted`` (``dataset.root``), set or not (``???``)."""
    parent, _, leaf = dotted.rpartition(".")
    node = OmegaConf.select(cfg, parent) if parent else cfg
    return node is not None and leaf in list(node.keys())  # ``in`` alone: False for a required value (???)


def own_groups(config_name: str) -> dict[str, str]:
    """The config groups the primary config uses (not Hydra's), with their default options."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name, return_hydra_config=True)
    return {group: option for group, option in cfg.hydra.runtime.choices.items() if not group.startswith("hydra")}


@pytest.mark.parametrize("name", sorted(HYDRA_SCRIPTS))
def test_help_is_one_screen_of_this_scripts_groups_options_and_examples(name, tmp_path):
    config_name, _ = HYDRA_SCRIPTS[name]
    target = hydra_targets()[name]
    done = subprocess.run(
        console_command(name, target, "--help"), cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr
    text = done.stdout
    assert len(text.splitlines()) <= HELP_LINES and text.startswith(f"{name} (python {config_name}.py in a checkout)")
    assert "--cfg job" in text and "--version" in text
    # the groups: exactly those this config uses, each with every option of its folder and the current choice
    groups = own_groups(config_name)
    listed = {}
    for line in section(text, "Config groups"):
        match = re.match(r"^  (\w+) +(.+?)  \(now (\w+)\)", line)
        if match:
            listed[match[1]] = (sorted(match[2].split(", ")), match[3])
    expected = {
        group: (sorted(p.stem for p in (CONF / group).glob("*.yaml")), option) for group, option in groups.items()
    }
    assert listed == expected
    others = {path.name for path in CONF.iterdir() if path.is_dir() and path.name != "hydra"} - set(groups)
    assert not [group for group in others if re.search(rf"(?<![\w./]){group}[=/]", text)], others
    # the options named are options of this config
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(config_name)
    options = re.findall(r"(?<![\w./-])([a-z_][\w.]*)=", "\n".join(section(text, "Options")))
    assert options and not [key for key in options if not has_key(cfg, key) and key not in groups], options
    # three examples of this script, each composing
    examples = [line.split("#")[0] for line in section(text, "Examples")]
    assert len(examples) == 3 and all(line.startswith(f"  {name} ") for line in examples), examples
    for line in examples:
        overrides = shlex.split(line)[1:]
        with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
            composed = compose(config_name, overrides)
        assert OmegaConf.to_container(composed, resolve=True), line


def test_the_full_config_is_still_one_flag_away(tmp_path):
    """``--cfg job`` prints the whole config, as before the help was made short."""
    command = console_command("icpflow-label", hydra_targets()["icpflow-label"], "--cfg", "job")
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    cfg = OmegaConf.create(done.stdout)
    assert {"dataset", "icpflow", "split", "out_dir", "shard_size"} <= set(cfg) and len(done.stdout.splitlines()) > 100
