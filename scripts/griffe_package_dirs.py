"""Griffe extension for the API reference (mkdocs.yml): subpackages that live outside their parent's directory.

``pyproject.toml`` installs the top-level ``envs/`` as ``qtl.envs`` (``[tool.setuptools] package-dir``). Griffe reads
the source tree, where ``qtl/`` has no ``envs`` directory; this extension loads each such directory once ``qtl`` is
loaded and makes it the member it is once installed, so that ``::: qtl.envs.cartpole.CartPoleSwingUpEnv`` resolves.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import griffe
import tomllib

ROOT = Path(__file__).resolve().parents[1]


def package_dirs() -> dict[str, str]:
    """Installed subpackage name → its directory in the tree, for the mapped ones with Python modules."""
    mapping = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]["package-dir"]
    return {name: path for name, path in mapping.items() if any((ROOT / path).glob("*.py"))}


class PackageDirs(griffe.Extension):
    """Graft each mapped directory onto its parent package as it is installed (see the module docstring)."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        """Once a parent package is loaded, load each of its mapped subpackages and attach it under its name."""
        for name, directory in package_dirs().items():
            parent, _, child = name.rpartition(".")
            if parent == pkg.path and child not in pkg.members:
                module = loader.load(directory, try_relative_path=False)
                pkg.set_member(child, module)
