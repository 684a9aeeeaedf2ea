"""Seeds: one for Python, numpy and torch, and the independent per-episode streams of a run."""

from __future__ import annotations

import random

import numpy as np
import torch

# Independent random streams, each derived from (seed, episode, stream): a resumed run draws
# exactly what an uninterrupted one would.
ENV_STREAM, ACTION_STREAM, MODEL_STREAM, SEARCH_STREAM, POLICY_INIT_STREAM = range(5)
# The fit of the target's own tuples that judges source samples (transfer.samples=relevance).
JUDGE_STREAM = 5


def seed_everything(seed: int) -> np.random.Generator:
    """Seed ``random``, numpy's global state and torch; return a numpy Generator from the same seed.

    The env is seeded through ``reset(seed=...)`` with :func:`derive_seed`, not here.
    """
    random.seed(seed)
    np.random.seed(seed)  # noqa: NPY002  (third-party code may draw from the global state)
    torch.manual_seed(seed)
    return np.random.default_rng(seed)


def derive_seed(seed: int, episode: int, stream: int) -> int:
    """A 32-bit seed for one random stream of one episode."""
    return int(np.random.SeedSequence([seed, episode, stream]).generate_state(1)[0])


def torch_generator(seed: int, episode: int, stream: int) -> torch.Generator:
    """A torch Generator seeded for one random stream of one episode."""
    return torch.Generator().manual_seed(derive_seed(seed, episode, stream))
