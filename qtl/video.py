"""An episode's frames as a clip, encoded: an animated GIF (Pillow), an MP4 (imageio-ffmpeg), a TensorBoard video.

A :class:`Clip` is frames `T x H x W x 3` (``uint8``) and their rate. The GIF is what TensorBoard's own
``add_video`` writes (a ``Summary.Image`` whose encoded image is GIF bytes) without moviepy: Pillow encodes it,
one palette for the whole clip (no flicker between frames). Pillow and imageio load only when a clip is encoded.
"""

from __future__ import annotations

import importlib.util
import io
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from qtl.errors import UserError

if TYPE_CHECKING:
    from tensorboard.compat.proto.summary_pb2 import Summary

GIF, MP4 = ".gif", ".mp4"
VIDEO_SUFFIXES = (GIF, MP4)  # what a clip can be written as, by the file's suffix
GIF_COLORS = 64  # one palette for every frame: the envs draw a few flat colours and their anti-aliased edges
PALETTE_SAMPLES = 8  # frames (evenly spaced) the palette is fitted to
GIF_TICK_MS = 10  # a GIF's frame duration is a whole number of hundredths of a second
MP4_BLOCK = 2  # H.264 (yuv420p) wants even sides: frames are padded to a multiple of this
FFMPEG_HINT = f"pip install imageio[ffmpeg] to write {MP4}, or write a {GIF}"


@dataclass(frozen=True)
class Clip:
    """Frames `T x H x W x 3` (``uint8``) shown at ``fps`` frames per second."""

    frames: np.ndarray
    fps: float

    def __post_init__(self) -> None:
        if self.frames.ndim != 4 or self.frames.shape[-1] != 3 or self.frames.dtype != np.uint8 or not len(self.frames):
            raise ValueError(f"a clip's frames are `T x H x W x 3` uint8 with T >= 1, got {self.frames.dtype} "
                             f"{self.frames.shape}")
        if not self.fps > 0:
            raise ValueError(f"a clip's fps must be > 0, got {self.fps}")

    @classmethod
    def of(cls, frames: list[np.ndarray], fps: float) -> Clip:
        """A clip of ``frames`` (each `H x W x 3` in [0, 255]), cut to the smallest frame's size.

        An env's frames may differ by a row or column where its view's size is rounded (the cart-pole's, as its
        view follows the cart): the extra edge pixels are dropped.
        """
        height = min(f.shape[0] for f in frames)
        width = min(f.shape[1] for f in frames)
        stacked = np.stack([np.asarray(f)[:height, :width, :3] for f in frames])
        return cls(np.clip(stacked, 0, 255).astype(np.uint8), float(fps))

    @property
    def frame_ms(self) -> int:
        """One frame's duration in a GIF: 1000/fps ms, in whole ticks of 10 ms (at least one)."""
        return max(GIF_TICK_MS, GIF_TICK_MS * round(1000.0 / self.fps / GIF_TICK_MS))

    def scaled(self, scale: float) -> Clip:
        """The clip with each side times ``scale`` (Lanczos); itself at 1."""
        if scale == 1.0:
            return self
        if not scale > 0:
            raise ValueError(f"scale must be > 0, got {scale}")
        from PIL import Image

        height, width = self.frames.shape[1:3]
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        return Clip(np.stack([np.asarray(Image.fromarray(f).resize(size, Image.LANCZOS)) for f in self.frames]),
                    self.fps)


def gif_bytes(clip: Clip) -> bytes:
    """The clip as an animated GIF (looping), one adaptive palette of :data:`GIF_COLORS` for every frame."""
    from PIL import Image

    picks = np.linspace(0, len(clip.frames) - 1, min(PALETTE_SAMPLES, len(clip.frames))).round().astype(int)
    palette = Image.fromarray(np.concatenate(clip.frames[picks], axis=0)).quantize(GIF_COLORS)
    images = [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.NONE) for f in clip.frames]
    out = io.BytesIO()
    images[0].save(out, format="GIF", save_all=True, append_images=images[1:], duration=clip.frame_ms, loop=0,
                   optimize=False, disposal=1)
    return out.getvalue()


def check_video_path(path: str | os.PathLike) -> Path:
    """``path`` if a clip can be written there by its suffix (``.gif``; ``.mp4`` with imageio-ffmpeg); else one line."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in VIDEO_SUFFIXES:
        raise UserError(f"cannot write {str(path)!r}: the file name must end in {' or '.join(VIDEO_SUFFIXES)}")
    if suffix == MP4 and not all(importlib.util.find_spec(m) for m in ("imageio", "imageio_ffmpeg")):
        raise UserError(f"cannot write {str(path)!r}: {FFMPEG_HINT}")
    return path


def write_clip(path: str | os.PathLike, clip: Clip) -> Path:
    """Write ``clip`` to ``path`` as its suffix says (:func:`check_video_path`), its folder made; the path."""
    path = check_video_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == GIF:
        path.write_bytes(gif_bytes(clip))
        return path
    import imageio.v2 as imageio

    height, width = clip.frames.shape[1:3]
    pad = ((0, 0), (0, -height % MP4_BLOCK), (0, -width % MP4_BLOCK), (0, 0))
    frames = np.pad(clip.frames, pad, mode="edge")
    imageio.mimwrite(path, list(frames), format="FFMPEG", fps=clip.fps, macro_block_size=MP4_BLOCK)
    return path


def frame_strip(clip: Clip, count: int, until: int | None = None) -> np.ndarray:
    """``count`` frames side by side `H x (count W) x 3`, evenly spaced over frames 0 … ``until`` (None: the last)."""
    if count < 1:
        raise ValueError(f"a strip needs at least one frame, got {count}")
    last = len(clip.frames) - 1 if until is None else min(until, len(clip.frames) - 1)
    picks = np.linspace(0, last, count).round().astype(int)
    return np.concatenate(clip.frames[picks], axis=1)


def write_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write an `H x W x 3` ``uint8`` image as a PNG, its folder made; the path."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path, format="PNG", optimize=True)
    return path


def video_summary(tag: str, clip: Clip) -> Summary:
    """The TensorBoard summary ``add_video`` writes for ``clip`` (an image whose encoding is the GIF), no moviepy."""
    from tensorboard.compat.proto.summary_pb2 import Summary

    height, width = clip.frames.shape[1:3]
    image = Summary.Image(height=height, width=width, colorspace=3, encoded_image_string=gif_bytes(clip))
    return Summary(value=[Summary.Value(tag=tag, image=image)])
