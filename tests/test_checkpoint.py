"""Per-episode checkpoints: a round trip keeps tensors and RNG states exactly; damaged input fails in one line."""

from __future__ import annotations

import random
import subprocess
import sys

import numpy as np
import pytest
import torch

from qtl.checkpoint import (
    CHECKPOINT_DIR,
    CHECKPOINT_FORMAT,
    LOCK_FILE,
    checkpoint_path,
    episodes_done,
    latest_checkpoint,
    load_checkpoint,
    prune_checkpoints,
    rng_state,
    run_checkpoint,
    run_lock,
    save_checkpoint,
    set_rng_state,
)
from qtl.errors import CheckpointError


def draws() -> tuple[float, float, float, torch.Tensor]:
    """One draw from each global generator: Python, numpy (uniform and Gaussian) and torch."""
    return random.random(), np.random.rand(), np.random.randn(), torch.rand(3)  # noqa: NPY002


def test_round_trip_keeps_the_payload_and_restores_every_rng_exactly(tmp_path):
    random.seed(1)
    np.random.seed(2)  # noqa: NPY002
    torch.manual_seed(3)
    np.random.randn()  # noqa: NPY002 (leaves a cached Gaussian: part of numpy's state)
    payload = {"theta": {"lengthscales": torch.arange(6.0, dtype=torch.float64).reshape(2, 3)},
               "metrics": [{"episode": 0, "return": 1.5}], "note": "text"}
    path = save_checkpoint(tmp_path, 4, payload)
    assert path == checkpoint_path(tmp_path, 4) == tmp_path / CHECKPOINT_DIR / "episode_0004.pt"
    assert sorted(p.name for p in path.parent.iterdir()) == ["episode_0004.pt"]  # no temporary file left
    expected = draws()

    draws()  # move every generator on, then restore
    state = load_checkpoint(path)
    set_rng_state(state["rng"])
    again = draws()
    assert again[:3] == expected[:3] and torch.equal(again[3], expected[3])
    assert state["format"] == CHECKPOINT_FORMAT and state["episode"] == 4
    assert torch.equal(state["theta"]["lengthscales"], payload["theta"]["lengthscales"])
    assert state["theta"]["lengthscales"].dtype == torch.float64
    assert state["metrics"] == payload["metrics"] and state["note"] == "text"


def test_rng_state_is_tensors_and_primitives(tmp_path):
    state = rng_state()
    torch.save(state, tmp_path / "rng.pt")
    assert torch.load(tmp_path / "rng.pt", weights_only=True)["numpy"]["pos"] == state["numpy"]["pos"]


def test_latest_checkpoint_is_the_highest_episode_and_ignores_other_files(tmp_path):
    for episode in (0, 2, 10):
        save_checkpoint(tmp_path, episode, {})
    (tmp_path / CHECKPOINT_DIR / "episode_0099.pt.tmp").write_bytes(b"half")  # a crash mid-write
    (tmp_path / CHECKPOINT_DIR / "episode_99.pt").write_bytes(b"not ours")
    assert latest_checkpoint(tmp_path).name == "episode_0010.pt"


def test_run_checkpoint_reads_the_newest_or_the_chosen_one_and_names_a_directory_without_a_run(tmp_path):
    for episode in (0, 1):
        save_checkpoint(tmp_path, episode, {"config": f"episodes: {episode}"})
    assert run_checkpoint(tmp_path)["episode"] == 1
    assert run_checkpoint(tmp_path, checkpoint_path(tmp_path, 0))["config"] == "episodes: 0"
    with pytest.raises(CheckpointError, match="does not exist"):
        run_checkpoint(tmp_path / "absent")
    with pytest.raises(CheckpointError, match="holds no checkpoints"):
        run_checkpoint(tmp_path / CHECKPOINT_DIR)


def test_prune_keeps_the_newest_and_episodes_done_counts_from_the_newest(tmp_path):
    assert episodes_done(tmp_path / "none") == 0
    for episode in (0, 1, 2, 3):
        save_checkpoint(tmp_path, episode, {})
    (tmp_path / CHECKPOINT_DIR / "episode_99.pt").write_bytes(b"not ours")
    assert prune_checkpoints(tmp_path, 0) == []  # 0: keep all
    assert [p.name for p in prune_checkpoints(tmp_path, 2)] == ["episode_0000.pt", "episode_0001.pt"]
    assert sorted(p.name for p in (tmp_path / CHECKPOINT_DIR).iterdir()) == [
        "episode_0002.pt", "episode_0003.pt", "episode_99.pt"]  # a foreign file is left alone
    assert episodes_done(tmp_path) == 4  # four episodes made, two checkpoints left
    assert prune_checkpoints(tmp_path, 5) == []
    with pytest.raises(ValueError, match="keep=-1"):
        prune_checkpoints(tmp_path, -1)


def test_missing_empty_or_foreign_runs_are_named(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        latest_checkpoint(tmp_path / "absent")
    with pytest.raises(CheckpointError, match=r"holds no checkpoints \(expected checkpoints/episode_NNNN.pt\)"):
        latest_checkpoint(tmp_path)
    with pytest.raises(CheckpointError, match="no checkpoint at"):
        load_checkpoint(tmp_path / "episode_0000.pt")
    torch.save({"weights": torch.ones(2)}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="is not a qtl run checkpoint"):
        load_checkpoint(tmp_path / "foreign.pt")
    torch.save({"format": CHECKPOINT_FORMAT, "version": 99}, tmp_path / "future.pt")
    with pytest.raises(CheckpointError, match="unsupported version 99"):
        load_checkpoint(tmp_path / "future.pt")


class _Opaque:
    """Not a tensor or primitive: a ``weights_only`` load refuses it."""


@pytest.mark.parametrize("damage", ["garbage", "truncated", "unsafe"])
def test_a_corrupt_checkpoint_is_a_one_line_checkpoint_error(tmp_path, damage):
    path = save_checkpoint(tmp_path, 0, {"data": torch.ones(100)})
    if damage == "garbage":
        path.write_bytes(b"garbage")
    elif damage == "truncated":
        path.write_bytes(path.read_bytes()[:200])
    else:
        torch.save({"format": CHECKPOINT_FORMAT, "object": _Opaque()}, path)
    with pytest.raises(CheckpointError, match="corrupt checkpoint") as caught:
        load_checkpoint(path)
    message = str(caught.value)
    assert "\n" not in message and str(path) in message and len(message) < 300, message
    assert isinstance(caught.value, ValueError)  # a UserError: bad input, not a crash


def test_run_lock_admits_one_process_at_a_time_and_is_released(tmp_path):
    with run_lock(tmp_path):
        assert "pid" in (tmp_path / LOCK_FILE).read_text()
        with pytest.raises(CheckpointError, match=r"in use by another qtl process \(pid \d+ on "), run_lock(tmp_path):
            pass
    with run_lock(tmp_path):  # released on exit, also after the refusal
        pass


def test_run_lock_is_released_when_the_holder_dies(tmp_path):
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from qtl.checkpoint import run_lock\n"
                               f"with run_lock({str(tmp_path)!r}):\n    print('held', flush=True); time.sleep(60)"],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(CheckpointError, match=f"pid {holder.pid}"), run_lock(tmp_path):
            pass
    finally:
        holder.kill()
        holder.wait()
    with run_lock(tmp_path):  # killed: the OS released its lock, nothing stale is left
        pass


def test_run_lock_makes_no_directory(tmp_path):
    with run_lock(tmp_path / "missing"):
        pass
    assert not (tmp_path / "missing").exists()
