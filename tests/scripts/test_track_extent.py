"""``scripts/research/track_extent.py``: extents per episode, their groups and crossing shares, on hand-made runs."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from qtl.checkpoint import save_checkpoint
from tests.scripts.load import script

track_extent = script("research/track_extent")


def checkpoint(peaks: list[float], successes: list[int]) -> dict:
    """A run's checkpoint: one random episode, then learned ones; x ramps to each peak (negative: to the left)."""
    states = []
    for peak in peaks:
        s = np.zeros((6, 4))
        s[:, 0] = np.linspace(0.0, peak, 6)
        states.append(torch.as_tensor(s))
    metrics = [{"kind": "random" if e == 0 else "policy", "success": ok} for e, ok in enumerate(successes)]
    return {"dataset": {"states": states}, "metrics": metrics}


def test_extents_groups_and_shares() -> None:
    extents = track_extent.episode_extents(checkpoint([-6.0, 0.8, 0.45, 0.3], [0, 0, 1, 1]), dim=0)
    assert [e["extent"] for e in extents] == pytest.approx([6.0, 0.8, 0.45, 0.3])  # |x|, left or right
    assert [e["kind"] for e in extents] == ["random", "policy", "policy", "policy"]
    grouped = track_extent.groups(extents, before=3)
    assert grouped["random"].tolist() == [6.0] and grouped["failed learned"].tolist() == [0.8]
    assert grouped["successful"].tolist() == pytest.approx([0.45, 0.3])
    assert grouped["learned before episode 3"].tolist() == pytest.approx([0.8, 0.45])  # episodes 1 and 2
    shares = track_extent.crossing_shares(grouped, [0.4, 0.5])
    assert shares[0.4]["successful"] == 0.5 and shares[0.5]["successful"] == 0.0
    assert shares[0.5]["random"] == 1.0 and shares[0.5]["failed learned"] == 1.0
    empty = track_extent.crossing_shares({"none": np.array([])}, [0.5])
    assert math.isnan(empty[0.5]["none"])


def test_runs_are_found_under_a_folder_and_read_from_their_newest_checkpoint(tmp_path: Path, capsys) -> None:
    for seed, peaks in enumerate([[7.0, 0.9], [5.0, 0.4]]):
        run = tmp_path / "bench" / f"seed_{seed}"
        save_checkpoint(run, 0, checkpoint(peaks[:1], [0]))
        save_checkpoint(run, 1, checkpoint(peaks, [0, seed]))
    found = dict(track_extent.local_checkpoints([tmp_path]))
    assert len(found) == 2 and all(len(c["metrics"]) == 2 for c in found.values())
    track_extent.main([str(tmp_path), "--limits", "0.5"])
    out = capsys.readouterr().out
    assert "2 runs, 4 episodes" in out and "| 0.5 " in out


def test_bad_options_are_refused(tmp_path: Path) -> None:
    with pytest.raises(SystemExit):
        track_extent.main([str(tmp_path), "--limits", "0"])
    with pytest.raises(SystemExit):
        track_extent.main([str(tmp_path), "--commit", "abc1234"])  # without --committed
    with pytest.raises(SystemExit):
        track_extent.main([str(tmp_path)])  # no run directories
