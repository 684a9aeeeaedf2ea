"""Benchmarks that make learning runs: options with Hydra overrides after them, runs in parallel, a run's figures."""

from __future__ import annotations

import argparse
import csv
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

from qtl.bench.record import display_path
from qtl.config.schema import TrainConfig
from qtl.launch import ensure_run
from qtl.metrics import area_under_curve, final_performance, first_success
from qtl.recorder import METRICS_FILE, TIMINGS_FILE

T = TypeVar("T")
R = TypeVar("R")


def parse_with_overrides(parser: argparse.ArgumentParser,
                         argv: Sequence[str] | None = None) -> tuple[argparse.Namespace, list[str]]:
    """The command's options and the Hydra overrides after them, a ``--`` separator dropped.

    A leftover ``-…`` token is a mistyped option (Hydra overrides are ``key=value``): refused in one line
    here, before any run starts, instead of reaching the runs' command lines and their recorded overrides.
    """
    args, rest = parser.parse_known_args(argv)
    overrides = [token for token in rest if token != "--"]
    unknown = [token for token in overrides if token.startswith("-")]
    if unknown:
        parser.error(f"unrecognised option(s) {' '.join(unknown)}: see --help (Hydra overrides are key=value)")
    return args, overrides


def add_learning_arguments(parser: argparse.ArgumentParser, *, seeds: Sequence[int], within: int,
                           runs_dir: Path) -> None:
    """The options every learning benchmark takes: --seeds, --within, --episodes, --jobs, --threads, --runs-dir.

    ``args.episodes`` is None unless given: the learned episodes per run are then ``--within`` − 1.
    """
    parser.add_argument("--seeds", type=int, nargs="+", default=list(seeds))
    parser.add_argument("--within", type=int, default=within,
                        help="success required within this many episodes, the random one included")
    parser.add_argument("--episodes", type=int, help="learned episodes per run (default: --within − 1)")
    parser.add_argument("--jobs", type=int, default=2, help="runs in parallel")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per run")
    parser.add_argument("--runs-dir", type=Path, default=runs_dir, help="where the runs are made (and reused)")


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


def read_csv(path: Path) -> list[dict[str, str]]:
    """The rows of a run's CSV file (``metrics.csv``, ``timings.csv``) as dicts of text."""
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def curve_figures(rows: Sequence[dict[str, str]]) -> dict:
    """A run's learning curve from its ``metrics.csv`` rows: returns, successes, first success, AUC, final value."""
    returns = [float(r["return"]) for r in rows]
    successes = [int(r["success"]) for r in rows]
    return {"returns": returns, "successes": successes, "first_success": first_success(successes),
            "auc": area_under_curve(returns), "final_performance": final_performance(returns)}


def initial_episodes(overrides: Sequence[str]) -> int:
    """The initial episodes of a run of ``overrides``: the last ``random_episodes=N`` among them, else the default."""
    given = [o.split("=", 1)[1] for o in overrides if o.lstrip("+").startswith("random_episodes=")]
    return int(given[-1]) if given else TrainConfig.random_episodes


def run_seed(seed: int, episodes: int, run_dir: Path, overrides: list[str], threads: int = 1) -> dict:
    """One full learning run through the CLI (reused or resumed when there is one); its per-episode figures.

    ``episodes``: the learned ones, after the initial ``random_episodes`` of ``overrides``.
    """
    total = initial_episodes(overrides) + episodes
    wall = ensure_run([f"seed={seed}", f"episodes={episodes}", *overrides], run_dir, total, threads=threads)
    rows = read_csv(run_dir / METRICS_FILE)[:total]
    timings = read_csv(run_dir / TIMINGS_FILE)[:total]
    learned = [t for t, r in zip(timings, rows, strict=True) if r["kind"] == "policy"]
    successes = [int(r["success"]) for r in rows]
    return {
        "seed": seed,
        "run_dir": display_path(run_dir),
        "returns": [float(r["return"]) for r in rows],
        "predicted_returns": [float(r["predicted_return"]) for r in rows],
        "successes": successes,
        "first_success": first_success(successes),
        "model_fit_s_per_episode": sum(float(t["model_fit_s"]) for t in learned) / max(len(learned), 1),
        "policy_search_s_per_episode": sum(float(t["policy_search_s"]) for t in learned) / max(len(learned), 1),
        "wall_s": wall,  # of this call: 0 for a reused run, the resumed part only for a resumed one
    }
