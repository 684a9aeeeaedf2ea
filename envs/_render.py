"""A tiny anti-aliased numpy rasteriser for the ``rgb_array`` frames of the environments.

No display and no GUI toolkit: every primitive is drawn by computing a per-pixel coverage in
``[0, 1]`` over its bounding box and alpha-blending its colour into a float image. Coordinates
are in *world* units (metres); a :class:`Canvas` maps them to pixels with a fixed scale and the
world's y axis pointing up.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise

import gymnasium
import numpy as np

Color = tuple[int, int, int]

WHITE: Color = (255, 255, 255)
BLACK: Color = (0, 0, 0)
GREY: Color = (150, 150, 150)
DARK_GREY: Color = (70, 70, 70)
LIGHT_GREY: Color = (225, 225, 225)
BLUE: Color = (52, 101, 164)
ORANGE: Color = (204, 121, 48)
RED: Color = (200, 40, 40)
GREEN: Color = (78, 154, 6)
BROWN: Color = (143, 110, 70)
SKY: Color = (235, 243, 250)

# Half a pixel: the width of the anti-aliased edge of every primitive.
_AA_HALF_WIDTH = 0.5
# Arrow heads are this many shaft widths long (and twice that wide).
_ARROW_HEAD_WIDTHS = 2.5


def warn_no_render_mode() -> None:
    """Gymnasium's warning for ``render()`` on an env made without a render mode."""
    gymnasium.logger.warn("render() called without a render_mode; make the env with render_mode='rgb_array'")


class Canvas:
    """An `H x W x 3` image showing the world rectangle `[x_min, x_max] x [y_min, y_max]`.

    The pixel scale is ``width / (x_max - x_min)``; the height follows from the y range so that
    one metre is as long horizontally as vertically.
    """

    def __init__(
        self,
        width: int,
        x_range: tuple[float, float],
        y_range: tuple[float, float],
        background: Color = WHITE,
    ) -> None:
        x_min, x_max = x_range
        y_min, y_max = y_range
        if not (x_max > x_min and y_max > y_min and width > 0):
            raise ValueError(f"empty canvas: width={width}, x_range={x_range}, y_range={y_range}")
        self.scale = width / (x_max - x_min)
        self.x_min = x_min
        self.y_max = y_max
        self.width = int(width)
        # Rounded to 1e-6 px first: a view that moves (the cart-pole's follows its cart) keeps one height, whatever
        # round-off its x range carries.
        self.height = round(round((y_max - y_min) * self.scale, 6))
        self._img = np.empty((self.height, self.width, 3), dtype=float)
        self._img[...] = np.asarray(background, dtype=float)

    # ---- coordinates -------------------------------------------------------------------------
    def to_pixels(self, points: np.ndarray) -> np.ndarray:
        """World points `... x 2` to pixel coordinates `... x 2` as (column, row) floats."""
        p = np.asarray(points, dtype=float)
        col = (p[..., 0] - self.x_min) * self.scale
        row = (self.y_max - p[..., 1]) * self.scale
        return np.stack([col, row], axis=-1)

    def _window(self, lo: np.ndarray, hi: np.ndarray) -> tuple[slice, slice, np.ndarray] | None:
        """Pixel window covering the pixel box [lo, hi] (col, row) and its pixel centres."""
        c0 = max(int(np.floor(lo[0])) - 1, 0)
        r0 = max(int(np.floor(lo[1])) - 1, 0)
        c1 = min(int(np.ceil(hi[0])) + 2, self.width)
        r1 = min(int(np.ceil(hi[1])) + 2, self.height)
        if c0 >= c1 or r0 >= r1:
            return None
        cols, rows = np.meshgrid(np.arange(c0, c1) + 0.5, np.arange(r0, r1) + 0.5)
        return slice(r0, r1), slice(c0, c1), np.stack([cols, rows], axis=-1)

    def _blend(self, rows: slice, cols: slice, coverage: np.ndarray, color: Color) -> None:
        a = np.clip(coverage, 0.0, 1.0)[..., None]
        region = self._img[rows, cols]
        region *= 1.0 - a
        region += a * np.asarray(color, dtype=float)

    # ---- primitives --------------------------------------------------------------------------
    def line(self, p0: Sequence[float], p1: Sequence[float], width: float, color: Color) -> None:
        """A segment with round caps, `width` in metres."""
        a, b = self.to_pixels(np.array([p0, p1], dtype=float))
        radius = max(0.5 * width * self.scale, _AA_HALF_WIDTH)
        win = self._window(np.minimum(a, b) - radius, np.maximum(a, b) + radius)
        if win is None:
            return
        rows, cols, pix = win
        ab = b - a
        denom = float(ab @ ab)
        t = np.zeros(pix.shape[:-1]) if denom == 0.0 else np.clip((pix - a) @ ab / denom, 0, 1)
        dist = np.linalg.norm(pix - (a + t[..., None] * ab), axis=-1)
        self._blend(rows, cols, radius + _AA_HALF_WIDTH - dist, color)

    def arrow(self, p0: Sequence[float], p1: Sequence[float], width: float, color: Color) -> None:
        """A shaft from `p0` to `p1` with a triangular head at `p1`, `width` in metres."""
        start, end = np.asarray(p0, dtype=float), np.asarray(p1, dtype=float)
        length = float(np.linalg.norm(end - start))
        if length == 0.0:
            return
        along = (end - start) / length
        across = np.array([-along[1], along[0]])
        head = min(_ARROW_HEAD_WIDTHS * width, 0.5 * length)
        neck = end - head * along
        self.line(start, neck, width, color)
        self.polygon(np.array([end, neck + head * across, neck - head * across]), color)

    def polyline(self, points: np.ndarray, width: float, color: Color) -> None:
        """Consecutive segments through world points `N x 2`."""
        pts = np.asarray(points, dtype=float)
        for p0, p1 in pairwise(pts):
            self.line(p0, p1, width, color)

    def circle(self, center: Sequence[float], radius: float, color: Color) -> None:
        """A filled disc, `radius` in metres."""
        c = self.to_pixels(np.asarray(center, dtype=float))
        r = max(radius * self.scale, _AA_HALF_WIDTH)
        win = self._window(c - r, c + r)
        if win is None:
            return
        rows, cols, pix = win
        dist = np.linalg.norm(pix - c, axis=-1)
        self._blend(rows, cols, r + _AA_HALF_WIDTH - dist, color)

    def polygon(self, points: np.ndarray, color: Color) -> None:
        """A filled *convex* polygon through world points `N x 2` (either orientation)."""
        p = self.to_pixels(np.asarray(points, dtype=float))
        win = self._window(p.min(axis=0), p.max(axis=0))
        if win is None:
            return
        rows, cols, pix = win
        edges = np.roll(p, -1, axis=0) - p
        # Signed area decides which side of each edge is inside.
        orientation = np.sign(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))
        if orientation == 0:
            return
        normals = orientation * np.stack([-edges[:, 1], edges[:, 0]], axis=-1)
        normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
        # Signed distance to each edge's line (positive inside); a pixel is as far inside as its
        # nearest edge.
        inside = np.einsum("...ek,ek->...e", pix[..., None, :] - p, normals).min(axis=-1)
        self._blend(rows, cols, inside + _AA_HALF_WIDTH, color)

    def rectangle(
        self,
        center: Sequence[float],
        size: tuple[float, float],
        color: Color,
        angle: float = 0.0,
    ) -> None:
        """A filled rectangle of `size` (width, height) in metres, rotated by `angle` radians."""
        half_w, half_h = 0.5 * size[0], 0.5 * size[1]
        corners = np.array([[-half_w, -half_h], [half_w, -half_h], [half_w, half_h], [-half_w, half_h]])
        rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        self.polygon(corners @ rot.T + np.asarray(center, dtype=float), color)

    def fill_below(self, xs: np.ndarray, ys: np.ndarray, color: Color) -> None:
        """Fill everything under the curve through world points (`xs`, `ys`), `xs` increasing."""
        cols = np.arange(self.width) + 0.5
        x_world = self.x_min + cols / self.scale
        y_curve = np.interp(x_world, np.asarray(xs, float), np.asarray(ys, float))
        row_curve = (self.y_max - y_curve) * self.scale
        rows = np.arange(self.height)[:, None] + 0.5
        self._blend(slice(None), slice(None), rows - row_curve[None, :] + _AA_HALF_WIDTH, color)

    def copy(self) -> Canvas:
        """An independent canvas with the same view and picture (to reuse a static background)."""
        twin = object.__new__(Canvas)
        twin.__dict__.update(self.__dict__)
        twin._img = self._img.copy()
        return twin

    def frame(self) -> np.ndarray:
        """The image as an `H x W x 3` `uint8` array (a fresh copy)."""
        return np.clip(np.rint(self._img), 0, 255).astype(np.uint8)
