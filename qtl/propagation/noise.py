"""Common random numbers of a particle rollout: the base noise of one draw, a fixed function of (seed, draw)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

# The base noise is drawn in this dtype and then converted to the propagation's.
NOISE_DTYPE = torch.float64
# The stream of the Gaussian-resampling noise within a draw (the start and step noise use stream 0).
RESAMPLING_STREAM = 1
# The stream of the pathwise functions' random numbers within a draw.
PATHWISE_STREAM = 2


class BaseNoise(NamedTuple):
    """One draw of base noise: ε_0 `P x D`, ε_1..ε_H `H x P x D`, and ε'_1..ε'_H `H x P x D` (or None)."""

    start: Tensor
    steps: Tensor
    resampling: Tensor | None


def per_step_noise(gen: torch.Generator, shape: tuple[int, int], horizon: int) -> Tensor:
    """``horizon`` standard normal draws of ``shape``, one per step in order: `H x ...` (float64)."""
    return torch.stack([torch.randn(shape, generator=gen, dtype=NOISE_DTYPE) for _ in range(horizon)])


def draw_seed(seed: int, draw: int, stream: int = 0) -> int:
    """A 32-bit seed for one stream of the base noise of one draw."""
    entropy = [seed, draw, stream] if stream else [seed, draw]  # stream 0 keeps the original seeds
    return int(np.random.SeedSequence(entropy).generate_state(1)[0])


def draw_base_noise(
    seed: int, draw: int, shape: tuple[int, int], horizon: int, *, resampling: bool, like: dict[str, object]
) -> BaseNoise:
    """The base noise of draw ``draw``: ε_0 and ε_1..ε_H of ``shape`` `P x D`, with ``resampling`` also ε'_1..ε'_H.

    Drawn in float64 whatever the dtype, so that every dtype sees the same numbers, one draw per step in order,
    so that the noise of step t does not depend on the horizon; then moved ``like`` (device and dtype).
    """
    gen = torch.Generator().manual_seed(draw_seed(seed, draw))
    start = torch.randn(shape, generator=gen, dtype=NOISE_DTYPE)
    steps = per_step_noise(gen, shape, horizon)
    redraws = None
    if resampling:
        gen = torch.Generator().manual_seed(draw_seed(seed, draw, RESAMPLING_STREAM))
        redraws = per_step_noise(gen, shape, horizon)
    return BaseNoise(start.to(**like), steps.to(**like), None if redraws is None else redraws.to(**like))
