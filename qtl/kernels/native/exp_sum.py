"""The native exp sum as an autograd op: `exp_sum.c` forward and backward, batch by per-item offsets."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import FunctionCtx, once_differentiable

from qtl.kernels.native.library import ExpSumLibrary


def item_offsets(t: Tensor, batch: torch.Size) -> Tensor:
    """Element offset of each batch item's matrix in ``t`` `*batch x r x c` (a view), `prod(batch)` int64."""
    offsets = torch.zeros((), dtype=torch.int64)
    for size, stride in zip(batch, t.stride()[: len(batch)], strict=True):
        offsets = offsets[..., None] + stride * torch.arange(size, dtype=torch.int64)
    return offsets.reshape(-1)


class NativeWeightedExpSum(torch.autograd.Function):
    """Σ_ij W_ij exp((A Bᵀ)_ij) by the compiled kernel; A `*batch x n x K`, B `*batch x m x K`, W `*batch x n x m`.

    The operands are views (expanded batch dimensions are fine) whose last two dimensions are
    contiguous; the gradients come back at the full batch shape and autograd sums them over the
    expanded dimensions. The reference twin is `qtl.kernels.exp_sum._WeightedExpSum`.
    """

    @staticmethod
    def forward(ctx: FunctionCtx, a: Tensor, b: Tensor, w: Tensor, library: ExpSumLibrary) -> Tensor:  # type: ignore[override]
        batch = a.shape[:-2]
        w_offsets = item_offsets(w, batch)
        # Items that share a broadcast W run one after another, while it is in cache.
        order = torch.argsort(w_offsets, stable=True)
        offsets = (item_offsets(a, batch), item_offsets(b, batch), w_offsets, order)
        ctx.save_for_backward(a, b, w)
        ctx.offsets, ctx.library = offsets, library
        return library.forward(a, b, w, offsets).view(batch)

    @staticmethod
    @once_differentiable
    def backward(ctx: FunctionCtx, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        a, b, w = ctx.saved_tensors
        needs = tuple(ctx.needs_input_grad[:3])
        grads = ctx.library.backward(a, b, w, ctx.offsets, grad.contiguous().reshape(-1), needs)
        shapes = (a.shape, b.shape, w.shape)
        return *(None if g is None else g.view(shape) for g, shape in zip(grads, shapes, strict=True)), None
