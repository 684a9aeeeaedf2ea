"""Clips encoded: GIF bytes read back frame by frame, MP4 where imageio-ffmpeg is, the strip, TensorBoard's summary."""

from __future__ import annotations

import importlib.util
import io

import numpy as np
import pytest
from PIL import Image

from qtl.errors import UserError
from qtl.video import Clip, check_video_path, frame_strip, gif_bytes, video_summary, write_clip, write_png


def moving_square(frames: int = 6, size: tuple[int, int] = (24, 40)) -> Clip:
    """A red square crossing a white frame, one column step per frame, a green bar appearing halfway."""
    images = np.full((frames, *size, 3), 255, dtype=np.uint8)
    for k in range(frames):
        images[k, 8:16, 4 * k : 4 * k + 8] = (200, 40, 40)
        if k >= frames // 2:
            images[k, 20:22, :] = (78, 154, 6)
    return Clip(images, fps=10.0)


def read_gif(data: bytes) -> tuple[list[np.ndarray], list[int]]:
    """The frames (RGB) and durations (ms) of an animated GIF."""
    image = Image.open(io.BytesIO(data))
    frames, durations = [], []
    for k in range(image.n_frames):
        image.seek(k)
        frames.append(np.asarray(image.convert("RGB")))
        durations.append(image.info["duration"])
    return frames, durations


def test_a_gif_holds_every_frame_at_the_clips_rate_and_its_colours():
    clip = moving_square()
    frames, durations = read_gif(gif_bytes(clip))
    assert len(frames) == len(clip.frames) and set(durations) == {100}
    for got, want in zip(frames, clip.frames, strict=True):
        assert got.shape == want.shape and np.abs(got.astype(int) - want).max() <= 8  # one shared palette, no dither


def test_a_frame_lasts_whole_hundredths_of_a_second():
    frames = moving_square().frames
    assert [Clip(frames, fps).frame_ms for fps in (10.0, 25.0, 20.0, 30.0, 1000.0)] == [100, 40, 50, 30, 10]


def test_frames_of_one_row_more_or_less_are_cut_to_the_smallest():
    clip = Clip.of([np.zeros((5, 7, 3)), np.full((6, 7, 4), 300.0)], fps=5)
    assert clip.frames.shape == (2, 5, 7, 3) and clip.frames.dtype == np.uint8 and clip.frames.max() == 255
    with pytest.raises(ValueError, match="T x H x W x 3"):
        Clip(np.zeros((2, 5, 7), dtype=np.uint8), fps=5)
    with pytest.raises(ValueError, match="fps must be > 0"):
        Clip(np.zeros((1, 5, 7, 3), dtype=np.uint8), fps=0)


def test_scaling_resizes_every_frame():
    clip = moving_square()
    assert clip.scaled(1.0) is clip and clip.scaled(0.5).frames.shape == (6, 12, 20, 3)


def test_a_strip_puts_evenly_spaced_frames_side_by_side(tmp_path):
    clip = moving_square()
    strip = frame_strip(clip, 3)
    assert strip.shape == (24, 120, 3)
    assert np.array_equal(strip[:, :40], clip.frames[0]) and np.array_equal(strip[:, 80:], clip.frames[-1])
    assert np.array_equal(frame_strip(clip, 2, until=2)[:, 40:], clip.frames[2])
    path = write_png(tmp_path / "sub" / "strip.png", strip)
    assert np.array_equal(np.asarray(Image.open(path).convert("RGB")), strip)


def test_only_gif_and_mp4_are_written(tmp_path, monkeypatch):
    with pytest.raises(UserError, match=r"must end in \.gif or \.mp4") as caught:
        check_video_path(tmp_path / "x.avi")
    assert "\n" not in str(caught.value)
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "imageio_ffmpeg" else real(name))
    with pytest.raises(UserError, match=r"pip install imageio\[ffmpeg\] to write \.mp4, or write a \.gif"):
        check_video_path(tmp_path / "x.mp4")
    path = write_clip(tmp_path / "deep" / "x.GIF", moving_square())
    assert path.read_bytes().startswith(b"GIF89a")


def test_an_mp4_holds_every_frame(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    import imageio.v2 as imageio

    clip = moving_square(frames=5, size=(23, 41))  # odd sides: padded to even for H.264
    path = write_clip(tmp_path / "x.mp4", clip)
    reader = imageio.get_reader(path)
    assert reader.get_meta_data()["fps"] == 10.0 and sum(1 for _ in reader) == 5


def test_the_tensorboard_summary_is_add_videos_image_of_gif_bytes():
    clip = moving_square()
    (value,) = video_summary("rollout/video", clip).value
    assert value.tag == "rollout/video"
    assert (value.image.height, value.image.width, value.image.colorspace) == (24, 40, 3)
    assert value.image.encoded_image_string == gif_bytes(clip)
