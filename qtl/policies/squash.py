"""Sine squashing of actions to [−u_max, u_max]: u = u_max (9 sin z + sin 3z)/8 (PILCO gSat)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from qtl.features import reference_trig_moments, trig_map, trig_stats, trig_terms
from qtl.gaussian import Gaussian, GaussianMap, MomentMatch, compose, full_batch, symmetrize
from qtl.kernels.engine import DEFAULT_ENGINE, Engine
from qtl.kernels.native import trig as native_trig
from qtl.policies.base import Policy

# u = u_max (SIN_WEIGHT sin z + SIN3_WEIGHT sin(SIN3_FREQ z)): the third-order Fourier
# truncation of a hard clip, monotone on [−π/2, π/2] with |u| <= u_max everywhere.
SIN_WEIGHT = 9.0 / 8.0
SIN3_WEIGHT = 1.0 / 8.0
SIN3_FREQ = 3.0


def sin_squash(z: Tensor, bound: Tensor) -> Tensor:
    """u = u_max (9 sin z + sin 3z)/8 elementwise, ``z`` `... x F`, ``bound`` `F` (u_max)."""
    return bound * (SIN_WEIGHT * z.sin() + SIN3_WEIGHT * (SIN3_FREQ * z).sin())


@functools.lru_cache(maxsize=16)
def _frequencies(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """c = [1, 3] as `2 x 1`, and [½, −½] as `2 x 1 x 1`."""
    freq = torch.tensor([1.0, SIN3_FREQ], dtype=dtype, device=device)
    half = torch.tensor([0.5, -0.5], dtype=dtype, device=device)
    return freq[:, None], half[:, None, None]


@functools.lru_cache(maxsize=16)
def _squash_map(num: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """[μ_z, vec Σ_z] `F + F²` to the trig statistics of φ = [z, 3z] (:func:`qtl.features.trig_map` of `2F`).

    The lift is linear: E φ_qf = c_q μ_f and cov[φ_qf, φ_rg] = c_q c_r Σ_fg with c = [1, 3].
    """
    freq = (1.0, SIN3_FREQ)
    lift = torch.zeros(num + num * num, 2 * num + 4 * num * num, dtype=dtype)
    for q, c_q in enumerate(freq):
        for f in range(num):
            lift[f, q * num + f] = c_q
            for r, c_r in enumerate(freq):
                for g in range(num):
                    lift[num + f * num + g, 2 * num + (q * num + f) * 2 * num + r * num + g] = c_q * c_r
    return (lift @ trig_map(2 * num, dtype, torch.device("cpu"))).to(device)


@dataclass(frozen=True)
class _SquashWeights:
    """The weights of u = Σ_q w_q sin(c_q z), c = [1, 3], w = [9/8 u_max, 1/8 u_max], for one bound."""

    mean: Tensor  # `... x 2 x F`, w_qf
    cov: Tensor  # `... x 2 x F x 2 x F`, w_qf w_rg
    slope: Tensor  # `... x 2 x F`, c_q w_qf (d u_f / d cos-term)

    @classmethod
    def of(cls, bound: Tensor) -> _SquashWeights:
        """The weights for ``bound`` `... x F` (u_max)."""
        freq, _ = _frequencies(bound.dtype, bound.device)
        mix = torch.stack([SIN_WEIGHT * bound, SIN3_WEIGHT * bound], dim=-2)  # ... x 2 x F
        return cls(mean=mix, cov=mix[..., :, :, None, None] * mix[..., None, None, :, :], slope=freq * mix)


def _squash_terms(mean: Tensor, cov: Tensor, weights: _SquashWeights) -> tuple[Tensor, Tensor, Tensor]:
    """E[u] `... x F`, cov[u] `... x F x F` (not symmetrized) and diag E[∂u/∂z] `... x F` for z ~ N(mean, cov).

    With φ = [z, 3z] (`2F`), E[sin φ] and cov[sin φ] are the exact trigonometric moments
    (:func:`qtl.features.trig_moments`, sines only: cov[sin φ_i, sin φ_j] = ½(G cos(μ_i − μ_j)
    − S cos(μ_i + μ_j))), and Stein's lemma gives E[∂u_f/∂z_f] = Σ_q c_q w_qf E[cos φ_qf].
    """
    num = mean.shape[-1]
    _, half = _frequencies(mean.dtype, mean.device)
    trig_mean, factors, angles = trig_terms(trig_stats(mean, cov, _squash_map(num, mean.dtype, mean.device)), 2 * num)
    sin_cov = (factors * angles.cos() * half).sum(-3).unflatten(-1, (2, num)).unflatten(-3, (2, num))
    trig_mean = trig_mean.unflatten(-2, (2, num))  # ... x 2 x F x 2: (E sin φ, E cos φ)
    out_mean = (trig_mean[..., 0] * weights.mean).sum(-2)
    out_cov = (sin_cov * weights.cov).sum((-4, -2))
    slope = (trig_mean[..., 1] * weights.slope).sum(-2)
    return out_mean, out_cov, slope


def _native_bound(bound: Tensor, mean: Tensor, *others: Tensor) -> bool:
    """Whether the compiled squashing takes these operands: float64 CPU, ``bound`` `F` without gradient."""
    fits = bound.shape == mean.shape[-1:] and not bound.requires_grad
    return fits and native_trig.applicable(bound, mean, *others)


def _reference_sin_squash_moments(state: Gaussian, bound: Tensor) -> MomentMatch:
    """:func:`sin_squash_moments`, reference formulation: the lift φ = [z, 3z] and the full (sin, cos) moments of φ."""
    state = state.expand()
    num = state.dim
    eye = torch.eye(num, dtype=state.dtype, device=state.mean.device)
    lift = torch.cat([eye, SIN3_FREQ * eye], dim=0)  # φ = A z = [z, 3z]: 2F x F
    phi_mean = state.mean @ lift.mT
    phi_cov = lift @ state.cov @ lift.mT
    trig_mean, trig_cov, trig_gain = reference_trig_moments(phi_mean, phi_cov)
    sines = slice(0, None, 2)  # trig_moments interleaves (sin, cos) per angle
    # u = L sin φ with L = [9/8 diag(u_max), 1/8 diag(u_max)].
    mix = torch.cat([SIN_WEIGHT * torch.diag(bound), SIN3_WEIGHT * torch.diag(bound)], dim=-1).to(phi_mean)
    mean = trig_mean[..., sines] @ mix.mT
    cov = mix @ trig_cov[..., sines, sines] @ mix.mT
    # Stein's lemma through the linear lift: E[∂u/∂z]ᵀ = Aᵀ E[∂ sin φ/∂φ]ᵀ Lᵀ.
    gain = lift.mT @ trig_gain[..., sines] @ mix.mT
    return MomentMatch(mean=mean, cov=symmetrize(cov), cross_cov=state.cov @ gain, gain=gain)


def sin_squash_moments(state: Gaussian, bound: Tensor, engine: Engine = DEFAULT_ENGINE) -> MomentMatch:
    """Exact mean, covariance and input–output terms of :func:`sin_squash` for z ~ N(μ, Σ), by ``engine``."""
    if not engine.fused:
        return _reference_sin_squash_moments(state, bound)
    state = full_batch(state)
    if engine.native and _native_bound(bound, state.mean, state.cov):  # one compiled call each way
        mean, cov, slope = native_trig.sin_squash_terms(state.mean, state.cov, bound)
        return MomentMatch(mean=mean, cov=cov, cross_cov=state.cov * slope, gain=torch.diag_embed(slope[..., 0, :]))
    mean, cov, slope = _squash_terms(state.mean, state.cov, _SquashWeights.of(bound.to(state.mean)))
    gain = torch.diag_embed(slope)  # sin_squash acts elementwise: E[∂u/∂z]ᵀ is diagonal
    return MomentMatch(mean=mean, cov=symmetrize(cov), cross_cov=state.cov * slope[..., None, :], gain=gain)


class SquashedPolicy(Policy):
    """u = u_max (9 sin z + sin 3z)/8 with z = policy(y); ψ is the wrapped policy's."""

    def __init__(self, policy: Policy, action_bound: float | Sequence[float] | Tensor) -> None:
        super().__init__()
        self.policy = policy
        self.input_dim, self.output_dim = policy.input_dim, policy.output_dim
        bound = torch.as_tensor(action_bound, dtype=torch.float64).flatten()
        if bound.numel() == 1:
            bound = bound.expand(self.output_dim).clone()
        if bound.shape != (self.output_dim,) or (bound <= 0).any():
            raise ValueError(f"action_bound must be positive, one per action ({self.output_dim})")
        self.register_buffer("action_bound", bound)

    def set_dropout(self, rate: float, generator: torch.Generator | None = None) -> None:
        """The wrapped policy's dropout (see :meth:`Policy.set_dropout`)."""
        self.policy.set_dropout(rate, generator)

    def forward(self, x: Tensor) -> Tensor:
        """Squashed actions `... x F` for features `... x D`."""
        return sin_squash(self.policy(x), self.action_bound.to(x))

    def actions(self, engine: Engine = DEFAULT_ENGINE) -> Callable[[Tensor], Tensor]:
        """The wrapped policy's ``actions(engine)``, squashed."""
        inner = self.policy.actions(engine)
        return lambda x: sin_squash(inner(x), self.action_bound.to(x))

    def prepare(self, engine: Engine = DEFAULT_ENGINE) -> GaussianMap:
        """The wrapped policy's moments, then exact squashing moments, chained (PILCO conCat); weights made once."""
        inner = self.policy.prepare(engine)
        weights: dict[torch.dtype, _SquashWeights] = {}

        def moments(state: Gaussian) -> MomentMatch:
            pre = inner(state)
            if not engine.fused:
                return compose(pre, _reference_sin_squash_moments(pre.output, self.action_bound.to(pre.mean)))
            if engine.native and _native_bound(self.action_bound, pre.mean, pre.cov):  # one compiled call each way
                mean, cov, slope = native_trig.sin_squash_terms(pre.mean, pre.cov, self.action_bound)
                return MomentMatch(mean=mean, cov=cov, cross_cov=pre.cross_cov * slope, gain=pre.gain * slope)
            dtype = pre.mean.dtype
            if dtype not in weights:
                weights[dtype] = _SquashWeights.of(self.action_bound.to(pre.mean))
            mean, cov, slope = _squash_terms(pre.mean, pre.cov, weights[dtype])
            # qtl.gaussian.compose with the diagonal gain diag(slope): a column scaling.
            slope = slope[..., None, :]
            return MomentMatch(mean=mean, cov=symmetrize(cov), cross_cov=pre.cross_cov * slope, gain=pre.gain * slope)

        return moments
