"""The fused weighted exponential sum Σ_ij W_ij exp((A Bᵀ)_ij) behind PILCO's second moments.

A moment-matching step spends most of its time here: E(E+1)/2 sums over `n x n` matrices per
step (the Q matrices of gp0/gp2, Deisenroth 2010, Sec. 2.3). This module holds the plain torch
implementation, blocked so that exp(A Bᵀ) is never stored whole; float64 CPU operands take its
native twin (`qtl/kernels/native/exp_sum.c`) when the engine says ``exp_sums="native"``.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from qtl.kernels import native
from qtl.kernels.engine import DEFAULT_ENGINE, Engine

# The `n x m` matrix exp(A Bᵀ) is formed in blocks of rows holding about this many entries
# (2 MiB in float64): a block stays in cache through product, exp, weighting and sum, which
# is several times faster than one pass per operation over the whole matrix.
BLOCK_ENTRIES = 2**18


def _sum_to_shape(t: Tensor, shape: torch.Size) -> Tensor:
    """Sum a broadcast gradient back to the shape of the operand it belongs to."""
    extra = t.dim() - len(shape)
    if extra > 0:
        t = t.sum(dim=tuple(range(extra)))
    dims = tuple(i for i, s in enumerate(shape) if s == 1 and t.shape[i] != 1)
    if dims:
        t = t.sum(dim=dims, keepdim=True)
    return t


def _block_rows(a: Tensor, b: Tensor) -> int:
    """Rows per block so that a block of exp(A Bᵀ), batch included, holds ~BLOCK_ENTRIES."""
    return max(1, BLOCK_ENTRIES // max(1, a[..., 0, 0].numel() * b.shape[-2]))


class _WeightedExpSum(torch.autograd.Function):
    """Σ_ij W_ij exp((A Bᵀ)_ij) for A `... x n x K`, B `... x m x K` (same shape), W `... x n x m`.

    The `n x m` matrix exp(A Bᵀ) is never stored: it is formed block by block of rows in the
    forward pass and again in the backward pass, so a rollout's autograd memory grows with n,
    not n², per step.
    """

    @staticmethod
    def forward(ctx, a: Tensor, b: Tensor, w: Tensor, rows: int) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(a, b, w)
        ctx.rows = rows
        b_t = b.mT
        total = None
        for start in range(0, a.shape[-2], rows):
            block = torch.matmul(a[..., start : start + rows, :], b_t).exp_()
            part = block.mul_(w[..., start : start + rows, :]).sum(dim=(-2, -1))
            total = part if total is None else total + part
        return total

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        a, b, w = ctx.saved_tensors
        rows = ctx.rows
        need_a, need_b, need_w = ctx.needs_input_grad[:3]
        scale = grad[..., None, None]
        grad_a = torch.empty_like(a) if need_a else None
        grad_b = torch.zeros_like(b) if need_b else None
        grad_w = []
        b_t = b.mT
        for start in range(0, a.shape[-2], rows):
            stop = start + rows
            block = torch.matmul(a[..., start:stop, :], b_t).exp_().mul_(scale)  # g · exp(A Bᵀ)
            if need_w:
                # A copy: the block is weighted in place below.
                grad_w.append(_sum_to_shape(block.clone(), w[..., start:stop, :].shape))
            if need_a or need_b:
                block.mul_(w[..., start:stop, :])
                if need_a:
                    grad_a[..., start:stop, :] = block @ b
                if need_b:
                    grad_b += block.mT @ a[..., start:stop, :]
        return grad_a, grad_b, torch.cat(grad_w, dim=-2) if need_w else None, None


def _native_fits(*tensors: Tensor) -> bool:
    """Whether the native kernel takes these operands: all float64 on the CPU."""
    return all(t.device.type == "cpu" and t.dtype == torch.float64 for t in tensors)


def _check_shapes(a: Tensor, b: Tensor, w: Tensor) -> None:
    """A `... x n x K`, B `... x m x K`, W `... x n x m`, or a ValueError naming the shapes."""
    matrices = min(a.dim(), b.dim(), w.dim()) >= 2
    if not matrices or a.shape[-1] != b.shape[-1] or w.shape[-2:] != (a.shape[-2], b.shape[-2]):
        raise ValueError(
            f"weighted_exp_sum needs A `... x n x K`, B `... x m x K`, W `... x n x m`; "
            f"got {tuple(a.shape)}, {tuple(b.shape)}, {tuple(w.shape)}"
        )


def _native_weighted_exp_sum(a: Tensor, b: Tensor, w: Tensor, library: native.ExpSumLibrary) -> Tensor:
    """The native path: operands expanded to the common batch as views (never copied per batch item)."""
    batch = torch.broadcast_shapes(a.shape[:-2], b.shape[:-2], w.shape[:-2])
    a, b, w = (t.contiguous() for t in (a, b, w))
    a = a.expand(*batch, *a.shape[-2:])
    b = b.expand(*batch, *b.shape[-2:])
    w = w.expand(*batch, *w.shape[-2:])
    return native.NativeWeightedExpSum.apply(a, b, w, library, torch.is_grad_enabled())


def weighted_exp_sum(
    a: Tensor, b: Tensor, w: Tensor, block_rows: int | None = None, *, engine: Engine = DEFAULT_ENGINE
) -> Tensor:
    """Σ_ij W_ij exp((A Bᵀ)_ij): `...` for A `... x n x K`, B `... x m x K`, W `... x n x m`.

    Batch dimensions broadcast. Float64 CPU operands take the compiled kernel when ``engine.exp_sums``
    is ``native`` (the engine resolved it loads); on the torch path ``block_rows`` (default: from
    ``BLOCK_ENTRIES``) sets how many rows of the `n x m` matrix are formed at a time. Autograd memory
    is O((n + m) K) on either path.
    """
    _check_shapes(a, b, w)
    if a.shape[-2] == 0 or b.shape[-2] == 0:  # an empty sum: zeros, with their (zero) gradients
        return (w * torch.exp(a @ b.mT)).sum((-2, -1))
    if engine.exp_sums == "native" and _native_fits(a, b, w):
        return _native_weighted_exp_sum(a, b, w, native.binding_once(native.ExpSumLibrary))
    batch = torch.broadcast_shapes(a.shape[:-2], b.shape[:-2])
    a, b = a.expand(*batch, *a.shape[-2:]), b.expand(*batch, *b.shape[-2:])
    return _WeightedExpSum.apply(a, b, w, block_rows or _block_rows(a, b))
