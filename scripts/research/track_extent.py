"""Research — how far the stored cart-pole episodes drive the cart: max |x| per episode, and who would cross a limit.

The data behind ``configs/task/cartpole_track.yaml``'s track limit. Reads every run directory (a folder with
``checkpoints/``) under the paths given, takes each run's newest checkpoint (its dataset holds every episode's real
states, its metrics each episode's success) and sorts the episodes into random, learned-and-successful and
learned-but-failed. For each candidate limit it prints the share of each group whose max |x| exceeds it. The paths
after ``--committed`` are read as ``--commit`` stores them (``git show``; nothing is checked out), e.g. the cart-pole
sweep's source runs, whose checkpoints commit 60fe2b8 keeps. The track limit's figures come from

    python scripts/research/track_extent.py runs/bench_cartpole/cartpole runs/bench_cartpole/cartpole-kinematic \
        --commit 60fe2b8 --committed docs/experiments/cartpole/source
        [--dim 0] [--limits 0.4 0.45 0.5 0.55 0.6 0.75 1.0] [--before 10] [--json PATH]
"""

from __future__ import annotations

import argparse
import io
import itertools
import json
import re
import subprocess
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np
import torch

from qtl.bench import ROOT, display_path, markdown_table
from qtl.checkpoint import run_checkpoint

DEFAULT_LIMITS = [0.4, 0.45, 0.5, 0.55, 0.6, 0.75, 1.0]
DEFAULT_BEFORE = 10  # "learned episodes before the tenth": the episodes a 10-episode benchmark sees
QUANTILES = (0.1, 0.25, 0.5, 0.75, 0.9)
_CHECKPOINT = re.compile(r"^(?P<run>.+)/checkpoints/episode_(?P<episode>\d{4})\.pt$")


def episode_extents(checkpoint: dict, dim: int) -> list[dict]:
    """Per episode of a run's checkpoint: its index, kind, success and max |x[dim]| over its real states."""
    states, metrics = checkpoint["dataset"]["states"], checkpoint["metrics"]
    return [{"episode": e, "kind": row["kind"], "success": bool(row["success"]),
             "extent": float(np.abs(np.asarray(s, dtype=float)[:, dim]).max())}
            for e, (s, row) in enumerate(zip(states, metrics, strict=True))]


def groups(extents: Sequence[dict], before: int) -> dict[str, np.ndarray]:
    """The extents of the random, the successful, the failed learned and the learned-before-``before`` episodes."""
    def pick(keep: Callable[[dict], bool]) -> np.ndarray:
        return np.array([e["extent"] for e in extents if keep(e)], dtype=float)

    return {
        "random": pick(lambda e: e["kind"] == "random"),
        "successful": pick(lambda e: e["kind"] == "policy" and e["success"]),
        "failed learned": pick(lambda e: e["kind"] == "policy" and not e["success"]),
        f"learned before episode {before}": pick(lambda e: e["kind"] == "policy" and e["episode"] < before),
    }


def crossing_shares(grouped: dict[str, np.ndarray], limits: Sequence[float]) -> dict[float, dict[str, float]]:
    """Per limit, the share of each group whose extent exceeds it (nan for an empty group)."""
    return {limit: {name: float(np.mean(values > limit)) if len(values) else float("nan")
                    for name, values in grouped.items()} for limit in limits}


def local_checkpoints(paths: Sequence[Path]) -> Iterator[tuple[str, dict]]:
    """(run, newest checkpoint) for every run directory under ``paths``."""
    for path in paths:
        for checkpoints in sorted(path.glob("**/checkpoints")):
            yield display_path(checkpoints.parent), run_checkpoint(checkpoints.parent)


def committed_checkpoints(commit: str, paths: Sequence[str]) -> Iterator[tuple[str, dict]]:
    """(run, newest checkpoint) for every run directory under ``paths`` as ``commit`` stores them."""
    def git(*args: str) -> bytes:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, check=True).stdout

    newest: dict[str, str] = {}
    for name in git("ls-tree", "-r", "--name-only", commit, "--", *paths).decode().splitlines():
        found = _CHECKPOINT.match(name)
        if found and name > newest.get(found["run"], ""):
            newest[found["run"]] = name
    for run, name in sorted(newest.items()):
        yield f"{run}@{commit}", torch.load(io.BytesIO(git("show", f"{commit}:{name}")), weights_only=True)


def main(argv: Sequence[str] | None = None) -> None:
    """Read the runs, print the extents' quantiles per group and the crossing shares per limit."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="*", type=Path, help="folders holding run directories")
    parser.add_argument("--commit", help="the commit that --committed reads from")
    parser.add_argument("--committed", nargs="+", default=[], help="folders holding run directories in --commit")
    parser.add_argument("--dim", type=int, default=0, help="the state dimension (the cart-pole's x: 0)")
    parser.add_argument("--limits", type=float, nargs="+", default=DEFAULT_LIMITS)
    parser.add_argument("--before", type=int, default=DEFAULT_BEFORE)
    parser.add_argument("--json", type=Path, help="also write the per-episode extents and the shares here")
    args = parser.parse_args(argv)
    if args.dim < 0 or args.before < 1 or min(args.limits) <= 0:
        parser.error("--dim must be >= 0, --before >= 1 and every limit > 0")
    if bool(args.commit) != bool(args.committed):
        parser.error("--commit and --committed go together")

    runs = itertools.chain(local_checkpoints(args.paths),
                           committed_checkpoints(args.commit, args.committed) if args.commit else ())
    per_run = {run: episode_extents(checkpoint, args.dim) for run, checkpoint in runs}
    if not per_run:
        parser.error("no run directories (folders with checkpoints/) under the paths given")
    extents = [e for run in per_run.values() for e in run]
    grouped = groups(extents, args.before)
    shares = crossing_shares(grouped, args.limits)

    print(f"{len(per_run)} runs, {len(extents)} episodes; max |x[{args.dim}]| per episode")
    print(markdown_table([[name, len(v), *(f"{q:.2f}" for q in np.quantile(v, QUANTILES)), f"{v.min():.2f}",
                           f"{v.max():.2f}"] for name, v in grouped.items() if len(v)],
                         ["episodes", "n", *(f"q{round(100 * q)}" for q in QUANTILES), "min", "max"], "lrrrrrrrr"))
    print()
    print(markdown_table([[f"{limit:g}", *(f"{100 * s:.0f} %" for s in share.values())]
                          for limit, share in shares.items()],
                         ["limit", *(f"{name} crossing" for name in grouped)], "lrrrr"))
    if args.json:
        args.json.write_text(json.dumps({"dim": args.dim, "commit": args.commit, "runs": per_run,
                                         "shares": {str(k): v for k, v in shares.items()}}, indent=2) + "\n")


if __name__ == "__main__":
    main()
