"""The native exp sum as an autograd op: `exp_sum.c` forward (with A/B gradients) and backward, by per-item offsets."""

from __future__ import annotations

import functools

import torch
from torch import Tensor
from torch.autograd.function import FunctionCtx, once_differentiable

from qtl.kernels.native.library import ExpSumLibrary


def item_offsets(t: Tensor, batch: torch.Size) -> Tensor:
    """Element offset of each batch item's matrix in ``t`` `*batch x r x c` (a view), `prod(batch)` int64."""
    return _offsets(tuple(batch), t.stride()[: len(batch)])


@functools.lru_cache(maxsize=256)
def _offsets(batch: tuple[int, ...], strides: tuple[int, ...]) -> Tensor:
    """Σ_d index_d · stride_d for every index of ``batch``, flattened (cached: a rollout repeats its shapes)."""
    offsets = torch.zeros((), dtype=torch.int64)
    for size, stride in zip(batch, strides, strict=True):
        offsets = offsets[..., None] + stride * torch.arange(size, dtype=torch.int64)
    return offsets.reshape(-1)


@functools.lru_cache(maxsize=256)
def _visit_order_for(batch: tuple[int, ...], w_strides: tuple[int, ...]) -> Tensor:
    """The items sorted stably by their W offset: those that share a broadcast W come one after another."""
    return torch.argsort(_offsets(batch, w_strides), stable=True)


class NativeWeightedExpSum(torch.autograd.Function):
    """Σ_ij W_ij exp((A Bᵀ)_ij) by the compiled kernel; A `*batch x n x K`, B `*batch x m x K`, W `*batch x n x m`.

    The operands are views (expanded batch dimensions are fine) whose last two dimensions are
    contiguous; the gradients come back at the full batch shape and autograd sums them over the
    expanded dimensions. ``grad_enabled`` is ``torch.is_grad_enabled()`` at the call (forward
    itself runs with grad mode off). When A or B needs a gradient and W does not (the GP
    dynamics), the forward pass also forms G_A = ∂s/∂A and G_B = ∂s/∂B and keeps only those, so
    backward is two products; when W needs one (the RBF policy), backward recomputes exp(A Bᵀ).
    The reference twin is `qtl.kernels.exp_sum._WeightedExpSum`.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: FunctionCtx, a: Tensor, b: Tensor, w: Tensor, library: ExpSumLibrary, grad_enabled: bool
    ) -> Tensor:
        batch = a.shape[:-2]
        w_strides = w.stride()[: len(batch)]
        # Items that share a broadcast W run one after another, while it is in cache.
        order = _visit_order_for(tuple(batch), w_strides)
        offsets = (item_offsets(a, batch), item_offsets(b, batch), item_offsets(w, batch), order)
        need_a, need_b, need_w = ctx.needs_input_grad[:3] if grad_enabled else (False, False, False)
        ctx.fused = (need_a or need_b) and not need_w
        value, g_a, g_b = library.forward(a, b, w, offsets, (need_a, need_b) if ctx.fused else (False, False))
        if ctx.fused:
            ctx.save_for_backward(g_a, g_b)
            ctx.shapes = (a.shape, b.shape)
        else:
            ctx.save_for_backward(a, b, w)
            ctx.offsets, ctx.library = offsets, library
        return value.view(batch)

    @staticmethod
    @once_differentiable
    def backward(ctx: FunctionCtx, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        if ctx.fused:
            scale = grad[..., None, None]  # ∂L/∂A = g · G_A, ∂L/∂B = g · G_B
            saved = zip(ctx.saved_tensors, ctx.shapes, strict=True)
            g_a, g_b = (None if g is None else scale * g.view(shape) for g, shape in saved)
            return g_a, g_b, None, None, None
        a, b, w = ctx.saved_tensors
        needs = tuple(ctx.needs_input_grad[:3])
        grads = ctx.library.backward(a, b, w, ctx.offsets, grad.contiguous().reshape(-1), needs)
        shapes = (a.shape, b.shape, w.shape)
        return *(None if g is None else g.view(shape) for g, shape in zip(grads, shapes, strict=True)), None, None
