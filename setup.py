"""The one thing pyproject.toml cannot say: the package list, where the top-level ``conf/`` (the Hydra configs, kept at
the top of the checkout) is the package ``icpflow_conf`` beside ``icpflow`` and ``fastflow3d`` (pyproject's
``package-dir`` and ``package-data`` map it and carry its YAML files), so that the console scripts of a wheel find their
configs (``icpflow.core.entry_points.config_path``). pyproject.toml's ``packages.find`` would replace this list: the
packages are found here. tests/project/test_console_scripts.py checks the wheel's files."""

from setuptools import find_namespace_packages, setup

setup(packages=[*find_namespace_packages(include=["icpflow*", "fastflow3d*"]), "icpflow_conf"])
