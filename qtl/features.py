"""Angle features: θ ↦ (sin θ, cos θ) on states and on Gaussian state distributions (PILCO's gTrig).

The convention is the project's one (``qtl.envs.rewards.augment_angles``): the augmented vector is
the non-angle dimensions in their order, then ``sin θ_a, cos θ_a`` for each ``a`` in
``angle_dims``; the raw angle is dropped.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from qtl.gaussian import Gaussian, MomentMatch, batch_matmul, full_batch, identity, symmetrize
from qtl.kernels.engine import DEFAULT_ENGINE, Engine
from qtl.kernels.native import trig as native_trig


@dataclass(frozen=True)
class _Signs:
    """Small constants of the trigonometric moments, made once per (dtype, device)."""

    one: Tensor  # 1, `()`
    minus_one: Tensor  # −1, `()`
    cos_minus_sin: Tensor  # [1, −1] as `2`: (E sin, E cos) flipped to (E cos, −E sin)


@functools.lru_cache(maxsize=16)
def _signs(dtype: torch.dtype, device: torch.device) -> _Signs:
    """The constants of :class:`_Signs` in ``dtype`` on ``device``."""
    pair = torch.tensor([1.0, -1.0], dtype=dtype, device=device)
    return _Signs(one=pair[0], minus_one=pair[1], cos_minus_sin=pair)


@functools.lru_cache(maxsize=16)
def _block_map(num: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """`4K² x 4K²` map from the products [cos, sin] x [G, S] x K x K to the interleaved `2K x 2K` covariance.

    Rows index (trig function f, factor q, i, j) of the products G cos(μ_i − μ_j), S cos(μ_i + μ_j),
    G sin(μ_i − μ_j), S sin(μ_i + μ_j); columns index (2i + s)(2K) + 2j + t for s, t ∈ {sin, cos}:
    cov[sin_i, sin_j] = ½(G cos d − S cos p), cov[sin_i, cos_j] = ½(G sin d + S sin p),
    cov[cos_i, sin_j] = ½(S sin p − G sin d), cov[cos_i, cos_j] = ½(G cos d + S cos p).
    """
    weights = {  # (s, t): ((f, q, weight), ...)
        (0, 0): ((0, 0, 0.5), (0, 1, -0.5)),
        (0, 1): ((1, 0, 0.5), (1, 1, 0.5)),
        (1, 0): ((1, 0, -0.5), (1, 1, 0.5)),
        (1, 1): ((0, 0, 0.5), (0, 1, 0.5)),
    }
    out = torch.zeros(2, 2, num, num, 2 * num, 2 * num, dtype=dtype)
    idx = torch.arange(num)
    for (s, t), terms in weights.items():
        for f, q, weight in terms:
            out[f, q, idx[:, None], idx[None, :], 2 * idx[:, None] + s, 2 * idx[None, :] + t] = weight
    return out.reshape(4 * num * num, 4 * num * num).to(device)


def _exp_times_expm1(log_scale: Tensor, s: Tensor) -> Tensor:
    """exp(log_scale) · (e^s − 1), accurate for small s and free of overflow for large |s|.

    Here |s| <= −log_scale (Cauchy–Schwarz: |σ_ij| <= (σ_i² + σ_j²)/2), so for s >= 0 the
    form −exp(log_scale + s)(e^{−s} − 1) never overflows, where exp(log_scale)·expm1(s) would
    give inf · 0 once σ² passes ~700. With sign = −1 for s >= 0 and 1 otherwise both cases are
    sign · expm1(sign · s) · exp(log_scale + max(s, 0)), whose factors stay finite with their gradients.
    """
    signs = _signs(s.dtype, s.device)
    sign = torch.where(s >= 0, signs.minus_one, signs.one)
    return torch.expm1(s * sign) * torch.exp(log_scale + s.clamp_min(0.0)) * sign


@functools.lru_cache(maxsize=16)
def trig_map(num: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """The linear map `(K + K²) x (2K + 6K²)` from [μ, vec Σ] to what :func:`trig_terms` reads.

    Columns: μ_k, −σ_k²/2, then `2 x K x K` blocks [μ_i − μ_j, μ_i + μ_j], [−(σ_i² + σ_j²)/2] twice,
    [σ_ij, −σ_ij]. All are linear in (μ, Σ), so that one matrix product forms them (and their gradient).
    """
    out = torch.zeros(num + num * num, 2 * num + 6 * num * num, dtype=dtype)
    pairs = out[:, 2 * num :].view(-1, 3, 2, num, num)  # (angles, log scale, signed cov) x (q) x i x j

    def cov_row(i: int, j: int) -> int:
        return num + i * num + j

    for k in range(num):
        out[k, k] = 1.0
        out[cov_row(k, k), num + k] = -0.5
    for i in range(num):
        for j in range(num):
            pairs[i, 0, :, i, j] += 1.0
            pairs[j, 0, 0, i, j] -= 1.0
            pairs[j, 0, 1, i, j] += 1.0
            pairs[cov_row(i, i), 1, :, i, j] -= 0.5
            pairs[cov_row(j, j), 1, :, i, j] -= 0.5
            pairs[cov_row(i, j), 2, 0, i, j] = 1.0
            pairs[cov_row(i, j), 2, 1, i, j] = -1.0
    return out.to(device)


def trig_stats(mean: Tensor, cov: Tensor, stats_map: Tensor) -> Tensor:
    """[μ, vec Σ] @ ``stats_map``: `... x (D + D²)` times `(D + D²) x S`, one matrix product."""
    batch = torch.broadcast_shapes(mean.shape[:-1], cov.shape[:-2])
    if mean.shape[:-1] != batch or cov.shape[:-2] != batch:
        mean, cov = mean.expand(*batch, *mean.shape[-1:]), cov.expand(*batch, *cov.shape[-2:])
    return torch.cat([mean, cov.flatten(-2)], dim=-1) @ stats_map


def trig_terms(stats: Tensor, num: int) -> tuple[Tensor, Tensor, Tensor]:
    """The pieces of the moments of (sin φ, cos φ), φ ~ N(μ `K`, Σ), from ``stats`` = [μ, vec Σ] @ :func:`trig_map`.

    Returns (E sin φ, E cos φ) `... x K x 2`, the factors [G, S] `... x 2 x K x K` with
    G = exp(−(σ_i² + σ_j²)/2)(e^{σ_ij} − 1) and S the same of −σ_ij, and the angles
    [μ_i − μ_j, μ_i + μ_j] `... x 2 x K x K`; E[sin φ] = exp(−σ²/2) sin μ.
    """
    mean, log_damp, pairs = stats.split([num, num, 6 * num * num], dim=-1)
    angles, log_outer, signed = pairs.unflatten(-1, (3, 2, num, num)).unbind(-4)
    trig_mean = torch.stack([mean.sin(), mean.cos()], dim=-1) * log_damp.exp()[..., None]
    return trig_mean, _exp_times_expm1(log_outer, signed), angles


def _trig_cov(factors: Tensor, angles: Tensor) -> Tensor:
    """cov[(sin φ_1, cos φ_1, …)] `... x 2K x 2K` from :func:`trig_terms`' factors and angles (not symmetrized)."""
    num = angles.shape[-1]
    products = factors[..., None, :, :, :] * torch.stack([angles.cos(), angles.sin()], dim=-4)  # ... x 2 x 2 x K x K
    block_map = _block_map(num, products.dtype, products.device)
    return (products.flatten(-4) @ block_map).unflatten(-1, (2 * num, 2 * num))


def _reference_exp_times_expm1(log_scale: Tensor, s: Tensor) -> Tensor:
    """exp(log_scale) · (e^s − 1), accurate for small s and free of overflow for large |s|.

    Here |s| <= −log_scale (Cauchy–Schwarz: |σ_ij| <= (σ_i² + σ_j²)/2), so for s >= 0 the
    form exp(log_scale + s)(1 − e^{−s}) never overflows, where exp(log_scale)·expm1(s) would
    give inf · 0 once σ² passes ~700. Both branches are evaluated on clamped arguments, so
    neither produces inf and their gradients stay finite.
    """
    pos, neg = s.clamp_min(0.0), s.clamp_max(0.0)
    return torch.where(s >= 0, torch.exp(log_scale + pos) * -torch.expm1(-pos), torch.exp(log_scale) * torch.expm1(neg))


def reference_trig_moments(mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`trig_moments`, reference formulation (stack → permute → reshape blocks; one expm1 product per sign).

    ``mean`` `... x K`, ``cov`` `... x K x K`. Returns the mean `... x 2K`, the covariance
    `... x 2K x 2K` and the expected Jacobian transposed `... x K x 2K` (Σ⁻¹ cov[φ, ·]).
    E[sin φ] = exp(−σ²/2) sin μ; the cross moments use E[cos(φ_i ± φ_j)], written with
    expm1 so that a vanishing covariance gives an exactly vanishing output covariance.
    """
    num = mean.shape[-1]
    var = torch.diagonal(cov, dim1=-2, dim2=-1)
    damp = torch.exp(-0.5 * var)
    e_sin, e_cos = damp * mean.sin(), damp * mean.cos()
    out_mean = torch.stack([e_sin, e_cos], dim=-1).flatten(-2)

    log_outer = -0.5 * (var[..., :, None] + var[..., None, :])  # log exp(−(σ_i² + σ_j²)/2)
    diff = mean[..., :, None] - mean[..., None, :]
    plus = mean[..., :, None] + mean[..., None, :]
    grow = _reference_exp_times_expm1(log_outer, cov)  # exp(−(σ_i² + σ_j²)/2) (e^{σ_ij} − 1)
    shrink = _reference_exp_times_expm1(log_outer, -cov)  # exp(−(σ_i² + σ_j²)/2) (e^{−σ_ij} − 1)
    ss = 0.5 * (grow * diff.cos() - shrink * plus.cos())
    cc = 0.5 * (grow * diff.cos() + shrink * plus.cos())
    sc = 0.5 * (shrink * plus.sin() + grow * diff.sin())  # cov[sin φ_i, cos φ_j]
    blocks = torch.stack([ss, sc, sc.mT, cc], dim=-1).unflatten(-1, (2, 2))  # ... K K 2 2
    out_cov = blocks.permute(*range(blocks.dim() - 4), -4, -2, -3, -1).reshape(*blocks.shape[:-4], 2 * num, 2 * num)

    eye = torch.eye(num, dtype=mean.dtype, device=mean.device)
    # d sin φ_k / dφ_k = cos φ_k, d cos φ_k / dφ_k = −sin φ_k.
    gain = torch.stack([eye * e_cos[..., None, :], -eye * e_sin[..., None, :]], dim=-1).flatten(-2)
    return out_mean, symmetrize(out_cov), gain


def trig_moments(mean: Tensor, cov: Tensor, engine: Engine = DEFAULT_ENGINE) -> tuple[Tensor, Tensor, Tensor]:
    """Exact moments of (sin φ_1, cos φ_1, …, sin φ_K, cos φ_K) for φ ~ N(mean, cov).

    ``mean`` `... x K`, ``cov`` `... x K x K`. Returns the mean `... x 2K`, the covariance
    `... x 2K x 2K` and the expected Jacobian transposed `... x K x 2K` (Σ⁻¹ cov[φ, ·]).
    E[sin φ] = exp(−σ²/2) sin μ; the cross moments use E[cos(φ_i ± φ_j)], written with
    expm1 so that a vanishing covariance gives an exactly vanishing output covariance. ``engine``: the
    reference or the fused formulation (:class:`qtl.kernels.engine.Engine`).
    """
    if not engine.fused:
        return reference_trig_moments(mean, cov)
    num = mean.shape[-1]
    trig_mean, factors, angles = trig_terms(trig_stats(mean, cov, trig_map(num, mean.dtype, mean.device)), num)
    # d sin φ_k / dφ_k = cos φ_k, d cos φ_k / dφ_k = −sin φ_k, on the diagonal k = k'.
    slopes = trig_mean.flip(-1) * _signs(mean.dtype, mean.device).cos_minus_sin  # ... x K x 2
    eye = identity(num, mean.dtype, mean.device)
    gain = (slopes[..., :, None, :] * eye[:, :, None]).flatten(-2)
    return trig_mean.flatten(-2), symmetrize(_trig_cov(factors, angles)), gain


@dataclass(frozen=True)
class _Layout:
    """Index tensors and constant matrices of the moments of one angle layout, per (dtype, device)."""

    other: Tensor  # O, the kept dimensions
    stats_map: Tensor  # (D + D²) x (O + 2K + 6K²): [μ, vec Σ] to μ_other and the trig statistics of the angles
    gain_base: Tensor  # D·(O + 2K): unit entries (other_j, j) of the gain, flattened
    gain_scatter: Tensor  # 2K x D·(O + 2K): slope (k, t) to entry (angle_k, O + 2k + t)


@functools.lru_cache(maxsize=32)
def _layout(state_dim: int, angle_dims: tuple[int, ...], dtype: torch.dtype, device: torch.device) -> _Layout:
    """The :class:`_Layout` of a ``state_dim``-D state with angles ``angle_dims``, built once."""
    other_dims = tuple(i for i in range(state_dim) if i not in set(angle_dims))
    dim, num, num_other = state_dim, len(angle_dims), len(other_dims)
    out_dim = num_other + 2 * num
    gain_base = torch.zeros(dim, out_dim, dtype=dtype)
    gain_base[list(other_dims), range(num_other)] = 1.0
    scatter = torch.zeros(num, 2, dim, out_dim, dtype=dtype)
    for k, a in enumerate(angle_dims):
        scatter[k, :, a, num_other + 2 * k : num_other + 2 * k + 2] = torch.eye(2, dtype=dtype)
    # [μ, vec Σ] of the state to [μ_other] and to [μ_angles, vec Σ_angles], then the trig map.
    select = torch.zeros(dim + dim * dim, num_other + num + num * num, dtype=dtype)
    select[list(other_dims), range(num_other)] = 1.0
    for k, a in enumerate(angle_dims):
        select[a, num_other + k] = 1.0
        for m, b in enumerate(angle_dims):
            select[dim + a * dim + b, num_other + num + k * num + m] = 1.0
    stats_map = select @ torch.block_diag(torch.eye(num_other, dtype=dtype), trig_map(num, dtype, torch.device("cpu")))
    return _Layout(
        other=torch.tensor(other_dims, dtype=torch.long, device=device),
        stats_map=stats_map.to(device),
        gain_base=gain_base.flatten().to(device),
        gain_scatter=scatter.reshape(2 * num, -1).to(device),
    )


class AngleFeatures:
    """The map x ↦ y = [x_other, sin θ_a, cos θ_a, …] for a raw state of dimension ``state_dim``."""

    def __init__(self, state_dim: int, angle_dims: Sequence[int] = ()) -> None:
        angle_dims = tuple(int(a) for a in angle_dims)
        if any(not 0 <= a < state_dim for a in angle_dims):
            raise ValueError(f"angle_dims {angle_dims} out of range for state_dim {state_dim}")
        if len(set(angle_dims)) != len(angle_dims):
            raise ValueError(f"angle_dims {angle_dims} contain duplicates")
        self.state_dim = state_dim
        self.angle_dims = angle_dims
        self.other_dims = tuple(i for i in range(state_dim) if i not in set(angle_dims))

    @property
    def output_dim(self) -> int:
        """Dimension of the augmented vector: D + number of angles."""
        return self.state_dim + len(self.angle_dims)

    def __call__(self, x: Tensor) -> Tensor:
        """Augment raw states `... x D` to `... x (D + K)`."""
        if x.shape[-1] != self.state_dim:
            raise ValueError(f"expected states `... x {self.state_dim}`, got {tuple(x.shape)}")
        angles = x[..., list(self.angle_dims)]
        trig = torch.stack([angles.sin(), angles.cos()], dim=-1).flatten(-2)
        return torch.cat([x[..., list(self.other_dims)], trig], dim=-1)

    def moments(self, state: Gaussian, engine: Engine = DEFAULT_ENGINE) -> MomentMatch:
        """Exact mean, covariance and input–output covariance of y for x ~ N(μ, Σ) (PILCO gTrig), by ``engine``."""
        if state.dim != self.state_dim:
            raise ValueError(f"expected a {self.state_dim}-D state, got {state.dim}-D")
        if not engine.fused:
            return self._reference_moments(state.expand())
        state = full_batch(state)
        mean, cov = state.mean, state.cov
        if not self.angle_dims:
            gain = identity(self.state_dim, mean.dtype, mean.device).expand(*cov.shape)
            return MomentMatch(mean=mean, cov=cov, cross_cov=cov, gain=gain)

        if engine.native and native_trig.applicable(mean, cov):  # the same maths, one compiled call each way
            out_mean, out_cov, cross_cov, gain = native_trig.angle_feature_moments(mean, cov, self.angle_dims)
            return MomentMatch(mean=out_mean, cov=out_cov, cross_cov=cross_cov, gain=gain)
        layout = _layout(self.state_dim, self.angle_dims, mean.dtype, mean.device)
        num_other = len(self.other_dims)
        stats = trig_stats(mean, cov, layout.stats_map)
        other_mean, stats = stats.split([num_other, stats.shape[-1] - num_other], dim=-1)
        trig_mean, factors, angles = trig_terms(stats, len(self.angle_dims))
        # Σ⁻¹ cov[x, y] = E[∂y/∂x]ᵀ: unit columns for the kept dims, the slopes (E cos, −E sin) on the angle rows.
        slopes = trig_mean.flip(-1) * _signs(mean.dtype, mean.device).cos_minus_sin  # ... x K x 2
        gain = torch.addmm(layout.gain_base, slopes.reshape(-1, slopes.shape[-2] * 2), layout.gain_scatter)
        gain = gain.view(*cov.shape[:-1], self.output_dim)  # ... x D x (D + K)
        cross_cov = batch_matmul(cov, gain)
        top = cross_cov.index_select(-2, layout.other)  # [cov[x_other, x_other], cov[x_other, trig]]
        bottom = torch.cat([top[..., num_other:].mT, _trig_cov(factors, angles)], dim=-1)
        out_cov = torch.cat([top, bottom], dim=-2)
        out_mean = torch.cat([other_mean, trig_mean.flatten(-2)], dim=-1)
        return MomentMatch(mean=out_mean, cov=symmetrize(out_cov), cross_cov=cross_cov, gain=gain)

    def _reference_moments(self, state: Gaussian) -> MomentMatch:
        """:meth:`moments`, reference formulation: index gathers, an eye-built gain, a cat of cats."""
        mean, cov = state.mean, state.cov
        other, angles = list(self.other_dims), list(self.angle_dims)
        eye = torch.eye(self.state_dim, dtype=mean.dtype, device=mean.device)
        if not angles:
            gain = eye.expand(*cov.shape)
            return MomentMatch(mean=mean, cov=cov, cross_cov=cov, gain=gain)
        trig_mean, trig_cov, trig_gain = reference_trig_moments(mean[..., angles], cov[..., angles, :][..., angles])
        # Σ⁻¹ cov[x, y] = E[∂y/∂x]ᵀ: unit columns for the kept dims, the trig gain on the angle rows.
        gain = torch.cat([eye[:, other].expand(*trig_gain.shape[:-2], -1, -1), eye[:, angles] @ trig_gain], dim=-1)
        cross_cov = cov @ gain  # D x (D + K)
        other_trig = cross_cov[..., other, len(other) :]  # cov[x_other, trig]
        out_cov = torch.cat(
            [
                torch.cat([cov[..., other, :][..., other], other_trig], dim=-1),
                torch.cat([other_trig.mT, trig_cov], dim=-1),
            ],
            dim=-2,
        )
        out_mean = torch.cat([mean[..., other], trig_mean], dim=-1)
        return MomentMatch(mean=out_mean, cov=symmetrize(out_cov), cross_cov=cross_cov, gain=gain)
