"""``qtl-play``: watch a run's policy — one episode on its task rendered to a GIF or MP4, the policy exported.

    qtl-play RUN_DIR [--episode N] [--seed S] [--out FILE.gif|FILE.mp4] [--scale F] [--export policy.pt] [--force]

Plays the policy of the checkpoint written after episode N (default: the newest, the final policy) for one
episode of the run's task, from the env reset with seed S. Without ``--seed`` that is the seed episode N itself
ran with, so a learned episode is replayed as it happened: the same states and the return ``metrics.csv`` records.
Every env step is a frame, the steps an action is held (``task.action_repeat``) included, at the env's rate.
``--export`` also saves the policy as a standalone torch module (:mod:`qtl.exported_policy`). Bad input (no run,
no such episode, an unknown suffix, a file that exists, an env that draws no frames) is one line, before any work.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

import torch

from qtl.build import DTYPES
from qtl.checkpoint import CHECKPOINT_DIR, checkpoint_path, latest_checkpoint
from qtl.episodes import Episode
from qtl.errors import UserError
from qtl.exported_policy import check_export_path, exported_policy, save_policy
from qtl.frames import rendered_episode
from qtl.runs import LoadedRun, load_run
from qtl.seeding import ENV_STREAM, derive_seed
from qtl.video import GIF, Clip, check_video_path, write_clip

PROG = "qtl-play"
PLAY_DIR = "play"  # <run dir>/play/: where the videos go by default
_CHECKPOINT = re.compile(r"^episode_(\d+)\.pt$")


@dataclass(frozen=True)
class Played:
    """One episode of a run's policy on its task: what it did, its frames, the reset seed, the checkpoint's episode."""

    episode: Episode
    clip: Clip
    seed: int
    checkpoint_episode: int


class _Parser(argparse.ArgumentParser):
    """argparse whose usage errors are :class:`UserError` (one line, like every other bad input)."""

    def error(self, message: str) -> NoReturn:
        raise UserError(f"{message} (see {PROG} --help)")


def parser() -> argparse.ArgumentParser:
    """The command line of ``qtl-play``."""
    p = _Parser(prog=PROG, description="Watch a run's policy: one episode on its task rendered to a GIF or MP4, the "
                "policy exported (--export).")
    p.add_argument("run_dir", type=Path, help="a run directory (qtl-train's: it holds checkpoints/)")
    p.add_argument("--episode", type=int, default=None, metavar="N",
                   help="play the policy of the checkpoint after episode N (default: the newest)")
    p.add_argument("--seed", type=int, default=None, metavar="S",
                   help="the env's reset seed (default: the seed episode N ran with, which replays it)")
    p.add_argument("--out", type=Path, default=None, metavar="FILE",
                   help=f"the video, .gif or .mp4 (default: <run dir>/{PLAY_DIR}/episode_NNNN.gif)")
    p.add_argument("--scale", type=float, default=1.0, metavar="F", help="scale the frames by this factor (default 1)")
    p.add_argument("--export", type=Path, default=None, metavar="POLICY",
                   help="also save the policy: .pt (TorchScript, torch.jit.load) or .pt2 (torch.export.load)")
    p.add_argument("--force", action="store_true", help="overwrite the files if they exist")
    return p


def checkpoint_of(run_dir: Path, episode: int | None) -> Path:
    """The checkpoint written after ``episode`` (None: the newest); a one-line error naming the ones there are."""
    if episode is None:
        return latest_checkpoint(run_dir)
    path = checkpoint_path(run_dir, episode)
    if path.is_file():
        return path
    latest_checkpoint(run_dir)  # no run there at all: its own one-line error
    held = sorted(int(m.group(1)) for p in (run_dir / CHECKPOINT_DIR).iterdir() if (m := _CHECKPOINT.match(p.name)))
    raise UserError(f"{str(run_dir)!r} holds no checkpoint of episode {episode}: it holds episodes "
                    f"{_ranges(held)} (keep_checkpoints may have deleted the others)")


def _ranges(numbers: Sequence[int]) -> str:
    """``0-3, 7, 9-10`` for sorted integers."""
    spans: list[list[int]] = []
    for n in numbers:
        if spans and n == spans[-1][1] + 1:
            spans[-1][1] = n
        else:
            spans.append([n, n])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in spans)


def episode_seed(run: LoadedRun, episode: int) -> int:
    """The reset seed the run gave its env for ``episode`` (:mod:`qtl.seeding`'s env stream)."""
    return derive_seed(int(run.config.seed), episode, ENV_STREAM)


def play(run: LoadedRun, seed: int | None = None) -> Played:
    """One episode of ``run``'s checkpoint policy on its task, rendered; ``seed`` None: the checkpoint episode's own."""
    seed = episode_seed(run, run.episode) if seed is None else seed
    episode, clip = rendered_episode(run.parts.task, run.parts.actor(run.policy()), seed)
    return Played(episode, clip, seed, run.episode)


def default_out(run_dir: Path, episode: int, seed: int | None) -> Path:
    """``<run dir>/play/episode_NNNN.gif`` (``…_seed_S.gif`` for another seed)."""
    stem = f"episode_{episode:04d}" + ("" if seed is None else f"_seed_{seed}")
    return run_dir / PLAY_DIR / f"{stem}{GIF}"


def refuse_existing(path: Path, force: bool) -> None:
    """A one-line error if ``path`` exists and ``force`` is not given."""
    if path.exists() and not force:
        raise UserError(f"{str(path)!r} exists: --force overwrites it")


def open_run(run_dir: Path, episode: int | None) -> LoadedRun:
    """The run read back at the checkpoint after ``episode`` (None: the newest), built on the CPU."""
    return load_run(run_dir, checkpoint=checkpoint_of(run_dir, episode), overrides=["device=cpu"])


def summary(out: Path, played: Played, run: LoadedRun, chosen_seed: bool) -> str:
    """One line: where the video went, whose policy from which start, the return and what the run recorded."""
    real = played.episode
    rows = [r for r in run.checkpoint.get("metrics", []) if int(r["episode"]) == played.checkpoint_episode]
    own = f"episode {played.checkpoint_episode}'s start (seed {played.seed})"
    start = f"seed {played.seed}" if chosen_seed else own
    line = (f"{out}: the policy of episode {played.checkpoint_episode} from {start}, return {real.rewards.sum():.2f} "
            f"over {real.length} steps ({len(played.clip.frames)} frames at {played.clip.fps:g} fps)")
    if rows and not chosen_seed:
        kind = rows[0].get("kind")
        line += (f"; the run recorded {float(rows[0]['return']):.2f}" if kind != "random" else
                 "; that episode ran random actions, this is the initial policy its checkpoint holds")
    return line


def main(argv: Sequence[str] | None = None) -> None:
    """``qtl-play``: bad input as one line on stderr (exit status 1); else the video (and policy) written."""
    try:
        print(_play(parser().parse_args(argv)))
    except UserError as err:
        sys.stderr.write(f"{PROG}: {str(err).splitlines()[0] if str(err) else type(err).__name__}\n")
        raise SystemExit(1) from None


def _play(args: argparse.Namespace) -> str:
    """Check everything, then play, write and export; the line to print."""
    if not args.scale > 0:
        raise UserError(f"--scale must be > 0, got {args.scale}")
    if args.out is not None:
        check_video_path(args.out)
        refuse_existing(args.out, args.force)
    if args.export is not None:
        check_export_path(args.export)
        refuse_existing(args.export, args.force)
    run = open_run(args.run_dir, args.episode)
    out = args.out if args.out is not None else default_out(args.run_dir, run.episode, args.seed)
    refuse_existing(out, args.force)
    torch.set_default_dtype(DTYPES[run.config.dtype])
    played = play(run, args.seed)
    write_clip(out, played.clip.scaled(args.scale))
    line = summary(out, played, run, args.seed is not None)
    if args.export is not None:
        task = run.parts.task
        save_policy(args.export, exported_policy(run.policy(), run.parts.features, task.action_center))
        line += f"\n{args.export}: the policy (state {task.state_dim} -> action {task.action_dim})"
    return line


if __name__ == "__main__":
    main()
