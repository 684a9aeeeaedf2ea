"""The posterior-cache tensors a propagator works on, from one model, one cache or a stack of them."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from qtl.models import GPPosteriorCache


def _tensors(cache: GPPosteriorCache) -> dict[str, Tensor]:
    theta = cache.hyperparameters
    return {
        "inputs": cache.inputs,  # n x D
        "K_inv": cache.K_inv,  # E x n x n
        "beta": cache.beta,  # E x n
        "lengthscales": theta.lengthscales,  # E x D
        "signal_variance": theta.signal_variance,  # E
        "noise_variance": theta.noise_variance,  # E
    }


def cache_tensors(model: GPPosteriorCache | Sequence[GPPosteriorCache] | Any) -> dict[str, Tensor]:
    """Tensors of a ``DynamicsGP`` (anything with ``posterior_cache()``), a cache, or caches stacked as `M`."""
    if hasattr(model, "posterior_cache"):
        model = model.posterior_cache()
    if isinstance(model, GPPosteriorCache):
        return _tensors(model)
    caches = list(model)
    shapes = {(c.inputs.shape, c.K_inv.shape) for c in caches}
    if len(shapes) != 1:
        raise ValueError(f"stacked GP caches must share n, D and E; got shapes {sorted(shapes)}")
    per_cache = [_tensors(c) for c in caches]
    return {name: torch.stack([t[name] for t in per_cache]) for name in per_cache[0]}
