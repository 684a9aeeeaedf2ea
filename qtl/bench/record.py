"""What a benchmark records beside its figures: the machine, date, commit and command, its JSON and its section."""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import re
import resource
import subprocess
import sys
from pathlib import Path

import torch

from qtl.report.paths import repository_root


def _clone() -> Path:
    """The working tree the benchmarks write into: the one holding this package (an editable install, as
    ``scripts/setup.sh`` makes it), else the one holding the current directory, else the current directory."""
    return repository_root(Path(__file__)) or repository_root(Path.cwd()) or Path.cwd()


ROOT = _clone()
BENCHMARKS_MD = ROOT / "docs" / "benchmarks.md"


def machine() -> dict[str, str | int]:
    """What the figures were measured on."""
    cpu = platform.processor() or platform.machine()
    try:
        lscpu = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        found = re.search(r"Model name:\s*(.+)", lscpu)
        cpu = found.group(1).strip() if found else cpu
    except (OSError, subprocess.CalledProcessError):
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count() or 0,
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "os": platform.platform(),
    }


def today() -> str:
    """The date of the measurement (UTC)."""
    return dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d")


def commit() -> str:
    """The checked-out commit (short hash), with '+changes' when tracked files outside docs/ differ from it."""
    def git(*args: str) -> str:  # not stripped: a porcelain line's status column may start with a space
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout

    changed = [line for line in git("status", "--porcelain", "--untracked-files=no").splitlines()
               if not line[3:].startswith("docs/")]
    return (git("rev-parse", "--short", "HEAD").strip() or "unknown") + ("+changes" if changed else "")


def peak_rss_mib() -> float:
    """Peak resident memory of this process so far, MiB (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def command_line() -> str:
    """How this script was invoked, relative to the repository root.

    An absolute path among the arguments, alone or as the value of a ``key=PATH`` token, is written as
    :func:`display_path` writes it, so that no path of the measuring machine is recorded.
    """
    return " ".join(["python", display_path(Path(sys.argv[0])), *map(relative_token, sys.argv[1:])])


def relative_token(token: str) -> str:
    """A command-line token with its absolute path (``/…`` or ``key=/…``) as :func:`display_path` writes it."""
    key, sep, value = token.partition("=")
    if sep and value.startswith("/"):
        return f"{key}={display_path(Path(value))}"
    return display_path(Path(token)) if token.startswith("/") else token


def display_path(path: Path | str) -> str:
    """How a recorded result names ``path``: relative to the repository root when it lies inside it.

    A relative path is taken from the working directory. A path outside the repository is written as
    ``…/<its name>``: the rest is a path of the measuring machine, which the results in ``docs/`` never record.
    """
    absolute = Path(os.path.abspath(path))
    for candidate in (absolute, absolute.resolve()):
        if candidate.is_relative_to(ROOT):
            return candidate.relative_to(ROOT).as_posix()
    return f"…/{absolute.name}"


def write_results(path: Path, info: dict, results: list) -> None:
    """The machine-readable results: ``info`` and ``results`` as indented JSON, parent folders made."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({**info, "results": results}, indent=2) + "\n")


def write_section(name: str, markdown: str) -> None:
    """Replace (or append) the section of ``docs/benchmarks.md`` fenced by markers for ``name``."""
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    block = f"{begin}\n{markdown.rstrip()}\n{end}"
    text = BENCHMARKS_MD.read_text() if BENCHMARKS_MD.exists() else "# Benchmarks\n"
    if begin in text and end in text:
        head, rest = text.split(begin, 1)
        text = head + block + rest.split(end, 1)[1]
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    BENCHMARKS_MD.write_text(text)
