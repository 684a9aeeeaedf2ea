"""One seed for Python, numpy and torch (the env is seeded through ``reset(seed=...)``)."""

from __future__ import annotations

import random

import numpy as np
import torch


def seed_everything(seed: int) -> np.random.Generator:
    """Seed ``random``, numpy's global state and torch; return a numpy Generator from the same seed."""
    random.seed(seed)
    np.random.seed(seed)  # noqa: NPY002  (third-party code may draw from the global state)
    torch.manual_seed(seed)
    return np.random.default_rng(seed)
