"""Seeding: one call seeds Python, numpy and torch; per-episode streams are independent and reproducible."""

from __future__ import annotations

import itertools
import random

import numpy as np
import torch

from qtl.seeding import (
    ACTION_STREAM,
    ENV_STREAM,
    MODEL_STREAM,
    POLICY_INIT_STREAM,
    SEARCH_STREAM,
    derive_seed,
    seed_everything,
    torch_generator,
)

STREAMS = (ENV_STREAM, ACTION_STREAM, MODEL_STREAM, SEARCH_STREAM, POLICY_INIT_STREAM)


def draws() -> tuple[float, float, float]:
    """One draw from each global generator."""
    return random.random(), float(np.random.rand()), float(torch.rand(()))  # noqa: NPY002


def test_seed_everything_makes_every_global_generator_repeat():
    rng = seed_everything(7)
    first, from_rng = draws(), rng.random()
    rng = seed_everything(7)
    assert draws() == first and rng.random() == from_rng
    seed_everything(8)
    assert all(a != b for a, b in zip(draws(), first, strict=True))


def test_streams_are_distinct_and_each_seed_is_32_bit_and_repeatable():
    assert len(set(STREAMS)) == len(STREAMS)
    seeds = {(s, e, k): derive_seed(s, e, k) for s, e, k in itertools.product((0, 1), (0, 1, 2), STREAMS)}
    assert len(set(seeds.values())) == len(seeds)  # no two (seed, episode, stream) share a seed
    assert all(0 <= v < 2**32 for v in seeds.values())
    assert all(derive_seed(*key) == v for key, v in seeds.items())


def test_torch_generator_draws_the_same_for_the_same_stream_only():
    a = torch.rand(5, generator=torch_generator(3, 2, MODEL_STREAM))
    b = torch.rand(5, generator=torch_generator(3, 2, MODEL_STREAM))
    c = torch.rand(5, generator=torch_generator(3, 2, SEARCH_STREAM))
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert torch_generator(3, 2, MODEL_STREAM).initial_seed() == derive_seed(3, 2, MODEL_STREAM)
