"""What the wheel installs (pyproject.toml): every package of the tree, the entry points' modules, no top-level envs."""

from __future__ import annotations

import importlib
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
SETUPTOOLS = PROJECT["tool"]["setuptools"]


def test_every_package_of_the_tree_is_installed():
    """A package missing from ``packages`` would be left out of the wheel, and fail only once installed."""
    directories = {"qtl": "qtl", **SETUPTOOLS["package-dir"]}
    found = set()
    for name, directory in directories.items():
        for init in (ROOT / directory).rglob("__init__.py"):
            parts = init.parent.relative_to(ROOT / directory).parts
            found.add(".".join([name, *parts]))
    assert found == set(SETUPTOOLS["packages"])
    assert not any(name.split(".")[0] != "qtl" for name in SETUPTOOLS["packages"])  # no top-level envs


def test_every_command_names_a_main_that_exists():
    for command, target in PROJECT["project"]["scripts"].items():
        module, _, function = target.partition(":")
        assert callable(getattr(importlib.import_module(module), function)), command
