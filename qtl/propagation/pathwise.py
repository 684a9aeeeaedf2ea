"""Pathwise GP posterior samples by Matheron's rule: one drawn function per particle and output.

Wilson et al. 2020, "Efficiently sampling functions from Gaussian process posteriors", Eq. 13:
a posterior sample is a prior sample plus a data-fitted update,

    f(x) = f̃(x) + k(x, X) (K + σ_ε²I)⁻¹ (y − f̃(X) − ε),    ε ~ N(0, σ_ε²I),

with the prior sample f̃ from L random Fourier features of the SE kernel (Eq. 3; Rahimi & Recht
2007): f̃(x) = Σ_l w_l φ_l(x), φ_l(x) = α √(2/L) cos(ω_lᵀ x + b_l), ω_l ~ N(0, Λ⁻¹),
b_l ~ U(0, 2π), w_l ~ N(0, 1). Since (K + σ_ε²I)⁻¹ y = β, the update of particle p is the vector
v_p = β − (K + σ_ε²I)⁻¹ (f̃_p(X) + ε_p) `n`, formed once per drawn function (O(n² + nL)), and then
f_p(x) = φ(x)ᵀ w_p + k(x, X) v_p costs O(n + L) per point and output instead of the O(n²) of the
marginal variance.

The function is a deterministic map of x: evaluated twice at the same x it gives the same value.
Its mean over draws is the posterior mean k β; its covariance is the posterior covariance of the
GP whose kernel is the features' φ(x)ᵀφ(x') (the SE kernel up to O(α²/√L)).

Everything here works on inputs already divided by the lengthscales (as
:func:`~qtl.kernels.gp_predictive` does): with x̃ = x / ℓ, ωᵀx = ω̃ᵀx̃ with ω̃ ~ N(0, I), so the
standard-normal frequencies are shared by every model of a stacked batch, whatever its θ.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor
from torch.autograd.function import FunctionCtx, once_differentiable

from qtl.kernels.engine import DEFAULT_ENGINE, Engine
from qtl.kernels.gp_predictive import se_kernel_rows
from qtl.kernels.native.pathwise import native_fits
from qtl.kernels.native.pathwise import path_values as native_path_values

# The dtype the functions' random numbers are drawn in, whatever the propagation's: float32, because torch
# draws float32 normals ~10× faster than float64 ones on the CPU (vectorised), and a draw takes E P (L + n)
# of them (~800k at P = 400, n = 250, L = 256: ~25 ms in float64 per evaluation with fresh draws). They are
# used in the propagation's dtype; standard normals rounded to float32 change nothing a sample can show.
DRAW_DTYPE = torch.float32


class FeatureDraw(NamedTuple):
    """Standard random numbers of one draw: ω̃ `E x L x D`, b `E x L`, w `E x P x L`, ε `E x n x P`."""

    frequencies: Tensor
    phases: Tensor
    weights: Tensor
    update_noise: Tensor


class MatheronPaths(NamedTuple):
    """P drawn functions per output, ready to evaluate (inputs over ℓ).

    ``frequencies`` ω̃ `E x L x D`; ``phases`` b `E x L`; ``weights`` α √(2/L) w_p `... x E x P x L`
    (the feature scale folded in); ``update`` v_p `... x E x P x n`.
    """

    frequencies: Tensor
    phases: Tensor
    weights: Tensor
    update: Tensor


def draw_features(
    generator: torch.Generator, num_outputs: int, input_dim: int, num_points: int, num_paths: int, num_features: int
) -> FeatureDraw:
    """The standard random numbers of one draw, in ``DRAW_DTYPE`` on the CPU, in a fixed order (ω̃, b, w, ε)."""
    like = {"generator": generator, "dtype": DRAW_DTYPE}
    frequencies = torch.randn(num_outputs, num_features, input_dim, **like)
    phases = 2 * math.pi * torch.rand(num_outputs, num_features, **like)
    weights = torch.randn(num_outputs, num_paths, num_features, **like)
    update_noise = torch.randn(num_outputs, num_points, num_paths, **like)
    return FeatureDraw(frequencies, phases, weights, update_noise)


def matheron_paths(
    draw: FeatureDraw,
    data: Tensor,
    beta: Tensor,
    K_inv: Tensor,
    signal_variance: Tensor,
    noise_variance: Tensor,
    dtype: torch.dtype | None = None,
    prior_inv: Tensor | None = None,
    update_root: Tensor | None = None,
    extra_noise: Tensor | None = None,
) -> MatheronPaths:
    """P posterior functions per output by Matheron's rule (Wilson et al. 2020, Eq. 13).

    ``draw``: the standard random numbers (any dtype; converted to ``data``'s); ``data`` `... x E x n x D`:
    the training inputs over ℓ; ``beta`` `... x E x n`; ``K_inv`` `... x E x n x n` = (K + σ_ε²I)⁻¹;
    ``signal_variance`` α² and ``noise_variance`` σ_ε² `... x E`. ``dtype``: the returned functions'
    (default: ``data``'s). A lower one (float32) also forms the prior sample at the data f̃_p(X) in it (the
    cos and the `n x L` by `L x P` product: well conditioned, a few ulp of Σ_l |W_pl|), while the solve with
    (K + σ_ε²I)⁻¹ stays in ``data``'s dtype and v is cast last. Not differentiable (θ and data fixed).
    A sparse GP (``data`` its inducing inputs Z, ``prior_inv`` K_mm⁻¹ and ``update_root`` R `... x E x m x m`
    given): v_p = β − K_mm⁻¹ f̃_p(Z) + R ξ_p (Wilson et al. 2020, sparse GPs: f̃ + k(·, Z) K_mm⁻¹ (u − f̃(Z)), u ~ q(u)),
    with ``draw``'s update noise as ξ. ``extra_noise`` c `... x E x n`: tuple i's noise is σ_ε² + c_i (exact GP with
    source samples), so ε_p ~ N(0, σ_ε²I + C) and ``K_inv`` = (K + σ_ε²I + C)⁻¹.
    """
    like = {"device": data.device, "dtype": data.dtype}
    dtype = data.dtype if dtype is None else dtype
    frequencies, phases, weights, update_noise = (t.to(**like) for t in draw)
    num_features = frequencies.shape[-2]
    scale = (2.0 * signal_variance / num_features).sqrt()[..., None, None]  # α √(2/L): `... x E x 1 x 1`
    weights = scale * weights  # ... x E x P x L
    # The functions' ω̃, b and W: the data dtype's values, rounded once to ``dtype``.
    frequencies, phases, weights = (t.to(dtype) for t in (frequencies, phases, weights))
    angle = data.to(dtype) @ frequencies.mT + phases[..., None, :]  # ... x E x n x L
    prior_at_data = (torch.cos(angle) @ weights.mT).to(data.dtype)  # f̃_p(X): ... x E x n x P
    if prior_inv is None:
        if extra_noise is None:
            residual = prior_at_data + noise_variance.sqrt()[..., None, None] * update_noise  # f̃_p(X) + ε_p
        else:
            residual = prior_at_data + (noise_variance[..., None] + extra_noise).sqrt()[..., None] * update_noise
        update = beta[..., :, None] - K_inv @ residual  # v_p = β − (K + σ_ε²I)⁻¹ (f̃_p(X) + ε_p): ... x E x n x P
    else:  # v_p = β − K_mm⁻¹ f̃_p(Z) + R ξ_p: ... x E x m x P
        update = beta[..., :, None] - prior_inv @ prior_at_data + update_root @ update_noise
    # `... x E x P x n`, row-contiguous, in one copy (the cast, when there is one, included).
    update = update.mT.to(dtype, memory_format=torch.contiguous_format).contiguous()
    return MatheronPaths(frequencies, phases, weights, update)


class _PathValues(torch.autograd.Function):
    """f_p(z̃_p) = φ(z̃_p)ᵀ w_p + k(z̃_p, X̃) v_p per output and particle; the gradient flows to ``z`` only.

    As :func:`~qtl.kernels.gp_predictive`, the forward pass also forms ∂f/∂z̃ (`... x E x P x D`)
    and keeps only that: no `P x n` or `P x L` tensor outlives the call.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: FunctionCtx,
        z: Tensor,
        data: Tensor,
        data_sq: Tensor,
        signal_variance: Tensor,
        paths: MatheronPaths,
    ) -> Tensor:
        frequencies, phases, weights, update = paths
        # Data-fitted part: k(z̃, X̃) v, the kernel rows as gp_predictive forms them.
        kern = se_kernel_rows(z, data, data_sq, signal_variance)  # ... x E x P x n
        kern_v = kern * update  # k_n v_pn (out of place: ``update`` may carry a larger batch)
        fitted = kern_v.sum(-1)
        # Prior part: Σ_l α √(2/L) w_pl cos(ω̃_lᵀ z̃ + b_l).
        angle = torch.matmul(z, frequencies.mT).add_(phases[..., None, :])  # ... x E x P x L
        prior = (torch.cos(angle) * weights).sum(-1)
        if ctx.needs_input_grad[0]:
            # ∂k_n/∂z̃ = k_n (d̃_n − z̃); ∂cos(ω̃ᵀz̃ + b)/∂z̃ = −sin(ω̃ᵀz̃ + b) ω̃.
            grad = kern_v @ data - z * fitted[..., None]
            grad = grad - (angle.sin_() * weights) @ frequencies
            ctx.save_for_backward(grad)
        return fitted + prior

    @staticmethod
    @once_differentiable
    def backward(ctx: FunctionCtx, grad_out: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        (grad,) = ctx.saved_tensors
        return grad * grad_out[..., None], None, None, None, None


def path_values(z: Tensor, data: Tensor, data_sq: Tensor, signal_variance: Tensor, paths: MatheronPaths,
                engine: Engine = DEFAULT_ENGINE) -> Tensor:  # fmt: skip
    """The drawn functions at ``z`` `... x E x P x D` (one point per particle, over ℓ): `... x E x P`.

    ``data`` `... x E x n x D` and ``data_sq`` `... x E x n` as in :func:`~qtl.kernels.gp_predictive`;
    ``signal_variance`` α² `... x E`; ``paths`` from :func:`matheron_paths`. Differentiable in ``z``.
    CPU operands all float64 or all float32 take the compiled kernel (`qtl/kernels/native/pathwise.c`, one
    body in both precisions) when ``engine.exp_sums`` is ``native``; everything else the torch ``_PathValues``
    (in the operands' dtype).
    """
    if engine.exp_sums == "native" and native_fits(z, data, signal_variance, *paths):
        return native_path_values(z, data, signal_variance, *paths)
    return _PathValues.apply(z, data, data_sq, signal_variance, paths)
