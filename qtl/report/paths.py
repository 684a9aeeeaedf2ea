"""Paths as the recorded files (``tables.json``, ``report.md``, ``experiment.yaml``) hold them: never a machine's.

A path inside a git working tree is recorded relative to that tree's top (``docs/experiments/cartpole``), which is
where the scripts are run from; one outside any working tree relative to the current directory when it lies
below it, else as it is (runs kept outside a repository are not committed).
"""

from __future__ import annotations

import os
from pathlib import Path


def repository_root(path: str | os.PathLike) -> Path | None:
    """The top of the git working tree holding ``path`` (the nearest folder above it with a ``.git``), or None."""
    here = Path(path).expanduser().resolve()
    for folder in (here, *here.parents):
        if (folder / ".git").exists():  # a folder in a clone, a file in a worktree
            return folder
    return None


def recorded_path(path: str | os.PathLike) -> str:
    """``path`` as a recorded file holds it: relative to its repository's top, else to the current directory where
    below it, else absolute (POSIX separators)."""
    here = Path(path).expanduser().resolve()
    for base in (repository_root(here), Path.cwd().resolve()):
        if base is not None and here.is_relative_to(base):
            return here.relative_to(base).as_posix() or "."
    return here.as_posix()


def recorded_override(override: str) -> str:
    """A Hydra override ``key=value`` with an absolute path as its value recorded as :func:`recorded_path` does (so
    ``sweep.root=<the clone, absolute>/docs/experiments/cartpole`` reads ``sweep.root=docs/experiments/cartpole``)."""
    key, sep, value = override.partition("=")
    if not sep or not os.path.isabs(os.path.expanduser(value)):
        return override
    return f"{key}={recorded_path(value)}"
