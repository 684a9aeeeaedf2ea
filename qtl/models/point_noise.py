"""Per-point noise: training tuple i of output e observed with variance σ_ε² + c_ei, c_ei >= 0 fixed.

A source tuple of relevance w ∈ (0, 1] (:mod:`qtl.transfer.samples`) enters the target's GP with the extra noise
c = σ̂_ε² (1/w − 1), σ̂_ε² the noise of the θ it was judged at: its noise is σ_ε²/w there, w = 1 pools it with the
target's own tuples and w → 0 leaves them alone. The form is GPyTorch's ``FixedNoiseGaussianLikelihood`` with
learned additional noise: σ_ε² stays one learned θ per output (the priors of :class:`~qtl.models.DynamicsGP` read it
unchanged) and c is data, fixed during evidence maximisation. A multiplicative σ_ε² s would not do: a tuple of huge
s still adds −½ log σ_ε² to the evidence and drags σ_ε² down, where σ_ε² + c with huge c adds nothing.
"""

from __future__ import annotations

from typing import Any

import torch
from gpytorch.likelihoods.noise_models import HomoskedasticNoise
from linear_operator.operators import DiagLinearOperator
from torch import Tensor


def checked_extra_noise(extra: Tensor, num_points: int, num_outputs: int) -> Tensor:
    """Extra noise c `n x E` (or `n`, one per tuple) as `E x n`, checked finite and >= 0 (a ValueError otherwise)."""
    extra = torch.as_tensor(extra)
    if extra.dim() == 1:
        extra = extra[:, None].expand(-1, num_outputs)
    if extra.shape != (num_points, num_outputs):
        raise ValueError(f"extra_noise must be `n x E` = ({num_points}, {num_outputs}) or `n`, one per training "
                         f"tuple, got shape {tuple(extra.shape)}")
    if not torch.isfinite(extra).all() or (extra < 0).any():
        raise ValueError("extra_noise must be finite and >= 0 (σ̂_ε² (1/w − 1) with relevance w in (0, 1]), got "
                         f"values in [{float(extra.min())}, {float(extra.max())}]")
    return extra.T.contiguous()


class PointNoise(HomoskedasticNoise):
    """GPyTorch's homoskedastic noise σ_ε² `E x 1`, plus ``extra`` c `E x n` at the n training inputs.

    As GPyTorch's ``FixedGaussianNoise`` does, a call whose shape has n points is taken to be at the training inputs
    (the marginal likelihood, the prediction strategy's train covariance); any other size gets σ_ε² alone.
    """

    def __init__(self, extra: Tensor, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.register_buffer("extra", extra)

    def forward(self, *params: Any, shape: torch.Size | None = None, **kwargs: Any) -> DiagLinearOperator:
        """diag(σ_ε² + c) at the training inputs (`E x n`), else σ_ε² I."""
        noise = super().forward(*params, shape=shape, **kwargs)
        if "noise" in kwargs or noise.shape[-1] != self.extra.shape[-1]:
            return noise
        return DiagLinearOperator(noise.diagonal(dim1=-2, dim2=-1) + self.extra)
