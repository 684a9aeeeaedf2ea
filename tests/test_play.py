"""qtl-play on a finished run: the episode replayed as a GIF, its return the recorded one, bad input in one line."""

from __future__ import annotations

import csv
import io
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from qtl.checkpoint import checkpoint_path
from qtl.loop import run
from qtl.play import main
from tests.helpers import tiny_config


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A finished tiny cart-pole run: one random and one learned episode, each action held two env steps."""
    path = tmp_path_factory.mktemp("played") / "run"
    run(tiny_config("episodes=1", "seed=4", "task.action_repeat=2"), path)
    return path


def play(capsys, *argv: str) -> tuple[int, str, str]:
    """``qtl-play argv``: its exit status, stdout and stderr."""
    try:
        main([str(a) for a in argv])
        status = 0
    except SystemExit as stop:
        status = int(stop.code)
    out, err = capsys.readouterr()
    return status, out, err


def gif_frames(path: Path) -> list[np.ndarray]:
    image = Image.open(io.BytesIO(path.read_bytes()))
    frames = []
    for k in range(image.n_frames):
        image.seek(k)
        frames.append(np.asarray(image.convert("RGB")))
    return frames


def recorded_return(run_dir: Path, episode: int) -> float:
    with open(run_dir / "metrics.csv", newline="") as f:
        return float(next(r for r in csv.DictReader(f) if int(r["episode"]) == episode)["return"])


def test_the_newest_policy_replays_its_episode_to_a_gif_a_frame_per_env_step(finished, capsys):
    status, out, err = play(capsys, finished)
    assert status == 0, err
    gif = finished / "play" / "episode_0001.gif"
    frames = gif_frames(gif)
    assert len(frames) == 2 * 8 + 1  # 8 learner steps of 2 env steps each, and the start
    assert len({f.tobytes() for f in frames}) > 1
    assert Image.open(gif).info["duration"] == 100  # the cart-pole's dt
    recorded = recorded_return(finished, 1)
    assert out.startswith(f"{gif}: the policy of episode 1 from episode 1's start")
    assert f"over 8 steps (17 frames at 10 fps); the run recorded {recorded:.2f}" in out
    assert out.count("\n") == 1


def test_another_episode_and_seed_go_to_their_own_file_and_nothing_is_overwritten_silently(finished, capsys):
    status, out, _ = play(capsys, finished, "--episode", 0, "--seed", 9, "--scale", 0.5)
    gif = finished / "play" / "episode_0000_seed_9.gif"
    assert status == 0 and out.startswith(f"{gif}: the policy of episode 0 from seed 9")
    assert gif_frames(gif)[0].shape == (106, 300, 3)
    status, _, err = play(capsys, finished, "--episode", 0, "--seed", 9)
    assert status == 1 and err == f"qtl-play: {str(gif)!r} exists: --force overwrites it\n"
    before = gif.stat().st_mtime_ns
    status, _, _ = play(capsys, finished, "--episode", 0, "--seed", 9, "--force")
    assert status == 0 and gif.stat().st_mtime_ns >= before and gif_frames(gif)[0].shape == (212, 600, 3)


def test_the_played_policy_is_exported_beside_the_video(finished, capsys, tmp_path):
    status, out, err = play(capsys, finished, "--out", tmp_path / "v.gif", "--export", tmp_path / "policy.pt")
    assert status == 0, err
    assert out.splitlines()[1] == f"{tmp_path / 'policy.pt'}: the policy (state 4 -> action 1)"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # torch 2.13 calls TorchScript deprecated
        policy = torch.jit.load(str(tmp_path / "policy.pt"))
    assert policy(torch.zeros(3, 4, dtype=torch.float64)).shape == (3, 1)


@pytest.mark.parametrize(("args", "message"), [
    (["{missing}"], "run directory '{missing}' does not exist"),
    (["{empty}"], "'{empty}' holds no checkpoints"),
    (["{run}", "--episode", "7"], "'{run}' holds no checkpoint of episode 7: it holds episodes 0-1"),
    (["{run}", "--out", "x.webm"], "cannot write 'x.webm': the file name must end in .gif or .mp4"),
    (["{run}", "--export", "p.onnx"], "cannot export to 'p.onnx': the file name must end in .pt"),
    (["{run}", "--scale", "0"], "--scale must be > 0, got 0.0"),
    (["{run}", "--episode", "one"], "argument --episode: invalid int value: 'one' (see qtl-play --help)"),
])
def test_bad_input_is_one_line_before_any_work(finished, capsys, tmp_path, args, message):
    names = {"missing": tmp_path / "absent", "empty": tmp_path, "run": finished}
    status, out, err = play(capsys, *[a.format(**names) for a in args])
    assert status == 1 and out == ""
    assert err.startswith(f"qtl-play: {message.format(**names)}") and err.count("\n") == 1


def test_keep_checkpoints_leaves_a_gap_the_error_names(finished, capsys, tmp_path):
    gappy = tmp_path / "gappy"
    (gappy / "checkpoints").mkdir(parents=True)
    for episode in (0, 1):
        os.link(checkpoint_path(finished, episode), checkpoint_path(gappy, 2 * episode))
    status, _, err = play(capsys, gappy, "--episode", 1)
    assert status == 1 and "it holds episodes 0, 2 (keep_checkpoints may have deleted the others)" in err


@pytest.mark.e2e  # the module's command line in a subprocess
def test_the_command_runs_as_a_program(finished, tmp_path):
    out = tmp_path / "e2e.gif"
    done = subprocess.run([sys.executable, "-m", "qtl.play", str(finished), "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith(f"{out}: the policy of episode 1") and out.read_bytes().startswith(b"GIF89a")
