"""Per-episode checkpoints of a run: data, θ, ψ, metrics and RNG states; enough to resume."""

from __future__ import annotations

import fcntl
import os
import random
import re
import socket
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch

from qtl.errors import CheckpointError

CHECKPOINT_DIR = "checkpoints"
CHECKPOINT_FORMAT = "qtl.run"
CHECKPOINT_VERSION = 1
_NAME = re.compile(r"^episode_(\d{4})\.pt$")
# Held (flock, exclusive) by the one process that works in a run directory; the OS releases it when that process ends.
LOCK_FILE = ".qtl.lock"


def rng_state() -> dict[str, Any]:
    """The global RNG states of Python, numpy and torch, as tensors and primitives."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()  # noqa: NPY002
    return {
        "python": random.getstate(),
        "numpy": {"kind": kind, "keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos),
                  "has_gauss": int(has_gauss), "cached": float(cached)},
        "torch": torch.get_rng_state(),
    }


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` returned."""
    random.setstate(state["python"])
    n = state["numpy"]
    np.random.set_state(  # noqa: NPY002
        (n["kind"], n["keys"].numpy().astype(np.uint32), n["pos"], n["has_gauss"], n["cached"])
    )
    torch.set_rng_state(state["torch"])


def checkpoint_path(run_dir: str | os.PathLike, episode: int) -> Path:
    """Where the checkpoint after ``episode`` lives."""
    return Path(run_dir) / CHECKPOINT_DIR / f"episode_{episode:04d}.pt"


def save_checkpoint(run_dir: str | os.PathLike, episode: int, payload: dict[str, Any]) -> Path:
    """Write the checkpoint after ``episode`` atomically (a crash never leaves half a file)."""
    path = checkpoint_path(run_dir, episode)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "episode": episode,
             "rng": rng_state(), **payload}
    tmp = path.with_suffix(".pt.tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)
    return path


def _checkpoints(run_dir: str | os.PathLike) -> list[Path]:
    """A run's episode checkpoints, oldest first (other files in the directory left out)."""
    return sorted(p for p in (Path(run_dir) / CHECKPOINT_DIR).glob("episode_*.pt") if _NAME.match(p.name))


def prune_checkpoints(run_dir: str | os.PathLike, keep: int) -> list[Path]:
    """Delete all but the newest ``keep`` checkpoints of a run (``keep`` = 0: delete none); the paths deleted."""
    if keep < 0:
        raise ValueError(f"keep={keep}: give the number of newest checkpoints to keep (0: all)")
    found = _checkpoints(run_dir)
    doomed = found[:-keep] if keep else []
    for path in doomed:
        path.unlink()
    return doomed


def episodes_done(run_dir: str | os.PathLike) -> int:
    """How many episodes a run directory has checkpointed: its newest checkpoint's episode + 1 (0 for none)."""
    found = _checkpoints(run_dir)
    return int(_NAME.match(found[-1].name).group(1)) + 1 if found else 0


def latest_checkpoint(run_dir: str | os.PathLike) -> Path:
    """The newest checkpoint of a run directory; a clear error when there is none."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise CheckpointError(f"run directory {str(run_dir)!r} does not exist")
    found = _checkpoints(run_dir)
    if not found:
        raise CheckpointError(f"{str(run_dir)!r} holds no checkpoints (expected {CHECKPOINT_DIR}/episode_NNNN.pt)")
    return found[-1]


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Read and check one checkpoint; a corrupt or foreign file gives a clear error."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {str(path)!r}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises many types for a damaged file
        raise CheckpointError(f"corrupt checkpoint {str(path)!r}: {type(err).__name__}: {_first_sentence(err)} "
                              "(delete it to resume from the checkpoint before)") from err
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{str(path)!r} is not a qtl run checkpoint")
    if state.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(f"{str(path)!r} has unsupported version {state.get('version')!r}")
    return state


def run_checkpoint(run_dir: str | os.PathLike, checkpoint: str | os.PathLike | None = None) -> dict[str, Any]:
    """The checkpoint a run directory is read back from: its newest, or ``checkpoint``; one-line error if it is none.

    The run's configuration in it (``"config"``) is as the run stored it; :func:`qtl.runs.read_run` migrates it.
    """
    return load_checkpoint(latest_checkpoint(run_dir) if checkpoint is None else checkpoint)


def _first_sentence(err: Exception) -> str:
    """The first sentence of an error's message, on one line (torch's load errors run over many lines)."""
    lines = str(err).strip().splitlines()
    return lines[0].split(". ")[0].rstrip(".") if lines else "no message"


def refuse_existing_run(run_dir: str | os.PathLike) -> None:
    """A fresh run must not start over a run directory that holds checkpoints (checked before anything is written)."""
    if any((Path(run_dir) / CHECKPOINT_DIR).glob("episode_*.pt")):
        raise CheckpointError(
            f"{str(run_dir)!r} already holds a run's checkpoints: resume={run_dir} continues it (resume=auto in "
            "a sweep), or choose another hydra.run.dir; nothing was overwritten"
        )


@contextmanager
def run_lock(run_dir: str | os.PathLike) -> Iterator[None]:
    """Work in ``run_dir`` alone: a second process (e.g. a sweep restarted over live workers) gets a CheckpointError.

    The lock is ``flock`` on ``<run_dir>/.qtl.lock``, released by the OS however the holder ends, so a killed run
    leaves nothing stale. A directory that does not exist yet holds no run: nothing to lock (and none is made).
    """
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        yield
        return
    handle = open(run_dir / LOCK_FILE, "a+", encoding="utf-8")  # held for the whole block
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "another process"
            raise CheckpointError(
                f"{str(run_dir)!r} is in use by another qtl process ({holder}): let it finish or stop it, then run "
                "again; nothing was written"
            ) from None
        handle.seek(0)
        handle.truncate()
        handle.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        handle.flush()
        yield
    finally:
        handle.close()  # closing the file releases the flock
