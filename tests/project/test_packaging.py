"""What a release carries, read from the files a user installs from: the dependencies every platform gets (from
pyproject.toml's markers), the version everywhere it is stated, the licence and the citation."""

import pytest
import yaml
from packaging.requirements import Requirement

import icpflow

from helpers.data import REPO

tomllib = pytest.importorskip("tomllib", reason="tomllib is in the standard library from Python 3.11")

PYPROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())

#: the platforms a user installs on, as pip's marker environment names them
PLATFORMS = {
    "Linux x86-64": {"platform_system": "Linux", "platform_machine": "x86_64", "sys_platform": "linux"},
    "Linux Arm": {"platform_system": "Linux", "platform_machine": "aarch64", "sys_platform": "linux"},
    "macOS Apple silicon": {"platform_system": "Darwin", "platform_machine": "arm64", "sys_platform": "darwin"},
    "macOS Intel": {"platform_system": "Darwin", "platform_machine": "x86_64", "sys_platform": "darwin"},
    "Windows": {"platform_system": "Windows", "platform_machine": "AMD64", "sys_platform": "win32"},
}
PYTHONS = ("3.10", "3.11", "3.12", "3.13")


def installed(platform: dict, python: str) -> set[str]:
    """The names of the base dependencies pip installs on ``platform`` with ``python``."""
    environment = {**platform, "python_version": python, "python_full_version": f"{python}.0", "os_name": "posix"}
    requirements = [Requirement(text) for text in PYPROJECT["project"]["dependencies"]]
    return {r.name for r in requirements if r.marker is None or r.marker.evaluate(environment)}


@pytest.mark.parametrize("python", PYTHONS)
@pytest.mark.parametrize("platform", PLATFORMS)
def test_every_platform_gets_exactly_one_open3d_and_torch_and_the_shipped_models_engine(platform, python):
    names = installed(PLATFORMS[platform], python)
    assert len({"open3d", "open3d-cpu"} & names) == 1, f"{platform}, Python {python}: {sorted(names)}"
    assert {"torch", "onnxruntime", "kiss-icp", "pypatchworkpp", "hdbscan", "numba"} <= names


def test_the_cpu_only_open3d_goes_where_it_has_wheels_only():
    assert "open3d-cpu" in installed(PLATFORMS["Linux x86-64"], "3.11")
    assert all("open3d-cpu" not in installed(PLATFORMS[name], "3.11") for name in PLATFORMS if name != "Linux x86-64")


def test_one_version_everywhere_it_is_stated():
    assert PYPROJECT["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "icpflow.__version__"}
    assert "version" in PYPROJECT["project"]["dynamic"]
    citation = yaml.safe_load((REPO / "CITATION.cff").read_text())
    assert str(citation["version"]) == icpflow.__version__ == "0.2.0"
    assert f"## {icpflow.__version__}" in (REPO / "CHANGELOG.md").read_text()


def test_the_licence_file_is_the_licence_declared():
    assert PYPROJECT["project"]["license"] == "MIT"
    assert (REPO / "LICENSE").read_text().startswith("MIT License")


def test_the_citation_credits_the_works_the_project_builds_on():
    citation = yaml.safe_load((REPO / "CITATION.cff").read_text())
    assert citation["cff-version"] == "1.2.0" and citation["license"] == "MIT"
    titles = " | ".join(reference["title"] for reference in citation["references"])
    for work in ("ICP-Flow", "ZeroFlow", "Scalable Scene Flow", "DeFlow", "KISS-ICP", "Patchwork++", "Hierarchical"):
        assert work in titles, work
    readme = (REPO / "README.md").read_text()
    for key in ("@inproceedings{lin2024icpflow", "@inproceedings{vedder2024zeroflow", "@article{vizzo2023kissicp"):
        assert key in readme, f"README.md: no BibTeX entry {key}"
