"""Shared plumbing of the ``scripts/bench_*.py`` benchmarks: machine facts and report sections."""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import re
import resource
import statistics
import subprocess
import sys
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

import torch

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS_MD = ROOT / "docs" / "benchmarks.md"


def parse_with_overrides(parser: argparse.ArgumentParser) -> tuple[argparse.Namespace, list[str]]:
    """The script's options and the Hydra overrides after them, a ``--`` separator dropped.

    A leftover ``-…`` token is a mistyped option (Hydra overrides are ``key=value``): refused in one line
    here, before any run starts, instead of reaching the runs' command lines and their recorded overrides.
    """
    args, rest = parser.parse_known_args()
    overrides = [token for token in rest if token != "--"]
    unknown = [token for token in overrides if token.startswith("-")]
    if unknown:
        parser.error(f"unrecognised option(s) {' '.join(unknown)}: see --help (Hydra overrides are key=value)")
    return args, overrides


T = TypeVar("T")
R = TypeVar("R")


def run_all(fn: Callable[[T], R], items: Sequence[T], jobs: int) -> list[R]:
    """``fn`` over ``items``, ``jobs`` at a time, in order; every item runs even when another fails.

    (``Executor.map`` cancels the items not yet started at the first failure it hands back, so one failed
    run would silently drop the rest of a sweep.) The failures, if any, are then raised as one error.
    """
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        futures = [pool.submit(fn, item) for item in items]
    errors = [(item, future.exception()) for item, future in zip(items, futures, strict=True)]
    failed = [(item, err) for item, err in errors if err is not None]
    if failed:
        lines = "\n".join(f"  {item!r}: {str(err).strip()}" for item, err in failed)
        raise RuntimeError(f"{len(failed)} of {len(items)} runs failed (the others finished):\n{lines}")
    return [future.result() for future in futures]


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


def model_label(row: dict) -> str:
    """How a result row's dynamics model reads in a table: 'exact' or 'sparse, m = <inducing inputs>'."""
    return f"sparse, m = {row['inducing']}" if row["model"] == "sparse" else "exact"


def mean_std(values: list[float], digits: int = 1) -> str:
    """Mean ± std over seeds ("—" for none, the value alone for one)."""
    if len(values) < 2:
        return f"{values[0]:.{digits}f}" if values else "—"
    return f"{statistics.mean(values):.{digits}f} ± {statistics.stdev(values):.{digits}f}"


def first_successes(per_seed: list[dict]) -> str:
    """The episode of each seed's first success ("—": none), space-separated."""
    return " ".join("—" if r["first_success"] is None else str(r["first_success"]) for r in per_seed)
