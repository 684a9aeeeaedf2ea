"""What a propagator is handed: the GP's posterior-cache tensors, checked against policy and reward."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import torch
from torch import Tensor

from qtl.features import AngleFeatures
from qtl.models import GPPosteriorCache
from qtl.policies.base import Policy
from qtl.propagation.base import DynamicsSource
from qtl.rewards import ExpectedSaturatingReward

log = logging.getLogger(__name__)
# The cache's entries that describe the outputs, the same in every cache of a stack: not stacked; the indices not cast.
UNSTACKED = ("outputs", "constant_outputs", "constant_delta")
INDICES = ("outputs", "constant_outputs")


def _tensors(cache: GPPosteriorCache) -> dict[str, Tensor]:
    """One cache's tensors by name: inputs, (K + σ_ε²I)⁻¹, β and θ (and a sparse GP's path update factors).

    ``outputs`` (`E`, integers): the state dimensions of the E outputs (0..E−1 when the cache names none);
    ``constant_outputs`` (`C`, integers) and ``constant_delta`` (`C`) where some outputs are deterministic.
    """
    theta = cache.hyperparameters
    num_outputs = cache.beta.shape[-2]
    outputs = tuple(range(num_outputs)) if cache.outputs is None else cache.outputs
    tensors = {
        "outputs": torch.tensor(outputs, dtype=torch.long, device=cache.beta.device),  # E
        "inputs": cache.inputs,  # n x D
        "K_inv": cache.K_inv,  # E x n x n
        "beta": cache.beta,  # E x n
        "lengthscales": theta.lengthscales,  # E x D
        "signal_variance": theta.signal_variance,  # E
        "noise_variance": theta.noise_variance,  # E
    }
    if cache.constant_outputs:  # outputs of a deterministic Δ (qtl.models.constant): their dims `C` and Δ `C`
        dims = torch.tensor(cache.constant_outputs, dtype=torch.long, device=cache.beta.device)
        tensors |= {"constant_outputs": dims, "constant_delta": cache.constant_delta.to(cache.beta)}
    if cache.extra_noise is not None and cache.prior_inv is None:  # an exact GP's per-tuple noise σ_ε² + c (pathwise)
        tensors["extra_noise"] = cache.extra_noise  # E x n
    if cache.prior_inv is not None:  # a sparse GP's: its pathwise update (m inducing inputs as n)
        tensors |= {"prior_inv": cache.prior_inv, "update_root": cache.update_root}  # E x m x m each
    return tensors


def cache_tensors(model: DynamicsSource) -> dict[str, Tensor]:
    """Tensors of a ``DynamicsGP`` (anything with ``posterior_cache()``), a cache, or caches stacked as `M`."""
    if hasattr(model, "posterior_cache"):
        model = model.posterior_cache()
    if isinstance(model, GPPosteriorCache):
        return _tensors(model)
    caches = list(model)
    shapes = {(c.inputs.shape, c.K_inv.shape, c.prior_inv is None, c.outputs, c.state_dim, c.constant_outputs,
               None if c.constant_delta is None else tuple(c.constant_delta.tolist()), c.extra_noise is None)
              for c in caches}
    if len(shapes) != 1:
        raise ValueError(f"stacked GP caches must share n, D, E, outputs (constant ones and their Δ) and kind "
                         "(exact or sparse); got "
                         f"{sorted(shapes, key=str)}")
    per_cache = [_tensors(c) for c in caches]
    return {name: per_cache[0][name] if name in UNSTACKED else torch.stack([t[name] for t in per_cache])
            for name in per_cache[0]}


def _state_dim(model: DynamicsSource) -> int | None:
    """The state dimension a model, a cache or stacked caches name (None: E, as a cache that names none)."""
    if hasattr(model, "posterior_cache") or isinstance(model, GPPosteriorCache):
        return getattr(model, "state_dim", None)
    return next(iter(model)).state_dim


def propagation_inputs(
    model: DynamicsSource,
    policy: Policy,
    reward: ExpectedSaturatingReward,
    angle_dims: Sequence[int],
    dtype: torch.dtype | None,
) -> tuple[dict[str, Tensor], AngleFeatures, torch.dtype]:
    """The model's tensors (detached, in ``dtype`` or the model's), the angle features, and the dtype.

    GP inputs must be [φ(x), u] (`D + K + F`) and outputs Δ in raw coordinates of the state dimensions
    ``data["outputs"]`` (`E`, all D of them unless the model names fewer); the policy must act on φ(x) and the
    reward score D-dimensional states. A mismatch raises ValueError.
    """
    data = cache_tensors(model)
    dtype = dtype or data["inputs"].dtype
    _warn_if_imprecise(data, dtype)
    data = {k: v if k in INDICES else v.detach().to(dtype) for k, v in data.items()}
    state_dim = _state_dim(model) or data["beta"].shape[-2]
    features = AngleFeatures(state_dim, angle_dims)
    gp_input_dim = data["inputs"].shape[-1]
    if gp_input_dim != features.output_dim + policy.output_dim:
        raise ValueError(
            f"GP input dimension {gp_input_dim} != features ({features.output_dim}) + actions ({policy.output_dim})"
        )
    if policy.input_dim != features.output_dim:
        raise ValueError(f"policy takes {policy.input_dim} inputs, the features have {features.output_dim}")
    if reward.state_dim != state_dim:
        raise ValueError(f"reward is for {reward.state_dim}-D states, the GP predicts {state_dim}-D")
    return data, features, dtype


def variance_roundoff_bound(data: dict[str, Tensor], dtype: torch.dtype) -> Tensor:
    """Bound on the round-off of the latent variance α² − k (K + σ_ε²I)⁻¹ kᵀ in ``dtype``, per output `... x E`.

    ‖k‖² <= n α⁴ and ‖(K + σ_ε²I)⁻¹‖ <= 1/σ_ε², so the quadratic form, and with it the difference, is
    off by up to ε n α⁴ / σ_ε² (ε: the dtype's machine epsilon).
    """
    n = data["inputs"].shape[-2]
    return torch.finfo(dtype).eps * n * data["signal_variance"].square() / data["noise_variance"]


def _warn_if_imprecise(data: dict[str, Tensor], dtype: torch.dtype) -> None:
    """Warn when ``dtype`` cannot resolve the GP's predictive variance down to its noise variance σ_ε²."""
    worst = float((variance_roundoff_bound(data, dtype) / data["noise_variance"]).max())
    if worst > 1.0:
        snr = float((data["signal_variance"] / data["noise_variance"]).max())
        if dtype == torch.float64:
            advice = (f"float64 is the most precise dtype: the fit's noise is too small for its data (α/σ_ε up to "
                      f"{snr ** 0.5:.3g}; the bound is a worst case, read the variances with care)")
        else:
            advice = "use dtype=float64"
        log.warning(
            "propagation in %s: the GP's latent variance may be off by up to %.3g × its noise variance "
            "(round-off bound ε n α⁴/σ_ε², signal-to-noise α²/σ_ε² up to %.3g at n = %d); predictive variances "
            "and the rollouts built on them are unreliable: %s",
            str(dtype).removeprefix("torch."), worst, snr, data["inputs"].shape[-2], advice,
        )
