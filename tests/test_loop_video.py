"""A run's TensorBoard video: the episode of each figure as GIF bytes, and nothing else of the run changed by it."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
import torch
from PIL import Image
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from qtl.checkpoint import latest_checkpoint, load_checkpoint
from qtl.loop import run
from qtl.recorder import VIDEO_TAG
from tests.helpers import tiny_config


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[bool, Path]:
    """The same tiny run (a figure every learned episode) with videos and without."""
    root = tmp_path_factory.mktemp("videos")
    for video in (True, False):
        run(tiny_config("episodes=1", "seed=2", f"video={str(video).lower()}"), root / str(video))
    return {video: root / str(video) for video in (True, False)}


def images(run_dir: Path) -> EventAccumulator:
    events = EventAccumulator(str(run_dir), size_guidance={"images": 0})
    events.Reload()
    return events


def test_each_figure_episode_has_its_video_as_gif_bytes_under_the_video_tag(runs):
    events = images(runs[True])
    assert VIDEO_TAG == "rollout/video" and VIDEO_TAG in events.Tags()["images"]
    videos = events.Images(VIDEO_TAG)
    assert [v.step for v in videos] == [1]  # the learned episode (figure_every=1)
    for video in videos:
        assert video.encoded_image_string.startswith(b"GIF89a")
        gif = Image.open(io.BytesIO(video.encoded_image_string))
        assert gif.n_frames == 8 + 1 and (video.width, video.height) == gif.size == (600, 212)
    assert VIDEO_TAG not in images(runs[False]).Tags()["images"]


def test_videos_change_nothing_the_run_computes(runs):
    with_video, without = runs[True], runs[False]
    assert (with_video / "metrics.csv").read_bytes() == (without / "metrics.csv").read_bytes()
    a, b = (load_checkpoint(latest_checkpoint(d)) for d in (with_video, without))
    assert a["rng"]["python"] == b["rng"]["python"] and a["rng"]["numpy"]["pos"] == b["rng"]["numpy"]["pos"]
    assert torch.equal(a["rng"]["numpy"]["keys"], b["rng"]["numpy"]["keys"])
    assert torch.equal(a["rng"]["torch"], b["rng"]["torch"])
    assert all(torch.equal(a["policy"][k], b["policy"][k]) for k in a["policy"])
