"""How a particle draws the GP's step: afresh from the predictive at every step, or along one function (pathwise)."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from qtl.kernels import gp_predictive
from qtl.kernels.engine import Engine
from qtl.propagation.noise import PATHWISE_STREAM, draw_seed
from qtl.propagation.pathwise import MatheronPaths, draw_features, matheron_paths, path_values

# Predictive variances at or below this are propagated as exactly 0 (standard deviation 1e-15):
# √v has an infinite derivative at 0, and its clamped form keeps the gradient finite.
SQRT_VARIANCE_FLOOR = 1e-30


class StepDraw(NamedTuple):
    """One step's GP draws per particle `... x P x E`: the predictive mean, its variance (None: pathwise), Δ."""

    mean: Tensor
    variance: Tensor | None
    delta: Tensor


# A rollout's sampler: the draws of step t at the scaled inputs z `... x E x P x D_in`.
StepSampler = Callable[[Tensor, int], StepDraw]


def safe_sqrt(var: Tensor) -> Tensor:
    """√v elementwise for v >= 0, exactly 0 with a zero (not NaN) gradient where v <= the floor."""
    positive = var > SQRT_VARIANCE_FLOOR
    return torch.where(positive, var.clamp_min(SQRT_VARIANCE_FLOOR).sqrt(), torch.zeros_like(var))


class GPTensors(NamedTuple):
    """What the samplers read of the GP: scaled data `... x E x n x D_in`, its norms², β, (K + σ_ε²I)⁻¹, α², σ_ε²."""

    data: Tensor
    data_sq: Tensor
    beta: Tensor
    K_inv: Tensor
    signal_variance: Tensor
    noise_variance: Tensor
    prior_inv: Tensor | None = None  # a sparse GP's
    update_root: Tensor | None = None
    extra_noise: Tensor | None = None  # c `... x E x n`: the training tuples' noise is σ_ε² + c (source samples)


class MarginalSampler:
    """Δ ~ N(m, v) drawn afresh at every step from the GP's predictive (Eq. 1-2), reparameterised: O(n²) per step.

    ``include_noise``: add σ_ε² to v.
    """

    name = "marginal"

    def __init__(self, gp: GPTensors, *, include_noise: bool) -> None:
        self.gp = gp
        self.include_noise = include_noise

    def rollout(self, draw: int, step_noise: Tensor) -> StepSampler:
        """The sampler of one rollout with the step noise ε_1..ε_H `H x P x E` of draw ``draw``."""

        def sample(z: Tensor, t: int) -> StepDraw:
            gp = self.gp
            mean, var = gp_predictive(z, gp.data, gp.data_sq, gp.beta, gp.K_inv, gp.signal_variance)  # ... x E x P
            var = var.clamp_min(0.0)  # round-off can make the latent variance slightly negative
            if self.include_noise:
                var = var + gp.noise_variance[..., None]
            delta = mean + safe_sqrt(var) * step_noise[t].mT  # Δ ~ N(m, v) reparameterised
            return StepDraw(mean.mT, var.mT, delta.mT)

        return sample

    def predictive_variance(self, variances: list[Tensor], mean: Tensor) -> Tensor:
        """The steps' predictive variances `... x P x H x E` from the per-step ones."""
        return torch.stack(variances, dim=-2)


class PathwiseSampler:
    """One function f_p per particle and output for the whole rollout (Matheron's rule): O(n + L) per step.

    ``seed``, ``num_particles`` and ``num_features`` L fix each draw's functions; ``eval_dtype``: the dtype they
    are evaluated in (the result comes back in ``dtype``); ``include_noise``: add σ_ε ε_t to f_p(x_t).
    """

    name = "pathwise"

    def __init__(
        self,
        gp: GPTensors,
        *,
        include_noise: bool,
        seed: int,
        num_particles: int,
        num_features: int,
        dtype: torch.dtype,
        eval_dtype: torch.dtype,
        engine: Engine,
    ) -> None:
        self.gp = gp
        self.include_noise = include_noise
        self.seed, self.num_particles, self.num_features = seed, num_particles, num_features
        self.dtype, self.eval_dtype, self.engine = dtype, eval_dtype, engine
        self.noise_std = gp.noise_variance.sqrt()  # σ_ε: ... x E
        # What the functions are evaluated with: float32 copies with eval_dtype float32 (else these).
        self.path_data, self.path_data_sq, self.path_signal_variance = (
            t.to(eval_dtype) for t in (gp.data, gp.data_sq, gp.signal_variance)
        )
        self._functions: tuple[int, MatheronPaths] | None = None

    def functions(self, draw: int) -> MatheronPaths:
        """The P functions per output of draw ``draw``: drawn and solved in ``dtype``, kept in ``eval_dtype``."""
        if self._functions is None or self._functions[0] != draw:
            gp = self.gp
            gen = torch.Generator().manual_seed(draw_seed(self.seed, draw, PATHWISE_STREAM))
            num_outputs, num_points, input_dim = gp.data.shape[-3:]
            features = draw_features(gen, num_outputs, input_dim, num_points, self.num_particles, self.num_features)
            paths = matheron_paths(features, gp.data, gp.beta, gp.K_inv, gp.signal_variance, gp.noise_variance,
                                   dtype=self.eval_dtype, prior_inv=gp.prior_inv, update_root=gp.update_root,
                                   extra_noise=gp.extra_noise)
            self._functions = (draw, paths)
        return self._functions[1]

    def rollout(self, draw: int, step_noise: Tensor) -> StepSampler:
        """The sampler of one rollout with the functions and the step noise ε_1..ε_H `H x P x E` of draw ``draw``."""
        functions = self.functions(draw)
        # The step noise σ_ε ε_t of every step in one product, `H x ... x P x E` (none without noise).
        noise_steps = None
        if self.include_noise:
            noise_steps = self.noise_std[..., None, :] * step_noise.view(
                step_noise.shape[0], *(1,) * (self.noise_std.dim() - 1), *step_noise.shape[1:])

        def sample(z: Tensor, t: int) -> StepDraw:
            f = path_values(z.to(self.eval_dtype), self.path_data, self.path_data_sq, self.path_signal_variance,
                            functions, self.engine)
            f = f.to(self.dtype).mT  # f_p: ... x P x E
            # the observation noise, independent per step, on top of f_p
            return StepDraw(f, None, f if noise_steps is None else f + noise_steps[t])

        return sample

    def predictive_variance(self, variances: list[Tensor], mean: Tensor) -> Tensor:
        """Given its function a particle's step varies by the noise alone: σ_ε² (or 0) every step, `... x P x H x E`."""
        var = self.gp.noise_variance if self.include_noise else torch.zeros_like(self.gp.noise_variance)
        return var[..., None, None, :].expand(*mean.shape[:-1], var.shape[-1])
