"""The native exp sum (`exp_sum.c`): its ctypes binding, and the autograd op over it by per-item offsets."""

from __future__ import annotations

import ctypes
import functools

import torch  # first: the kernel then shares the libgomp torch has loaded
from torch import Tensor
from torch.autograd.function import FunctionCtx, once_differentiable

from qtl.kernels.native.loader import load_binding

_PTR, _INT64, _INT = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
# a, b, w, off_a, off_b, off_w, order, items, n, m, k
_COMMON = [_PTR] * 7 + [_INT64] * 4


def _ptr(t: Tensor | None) -> int | None:
    """The address of a tensor's first element (None for a gradient that is not wanted)."""
    return None if t is None else t.data_ptr()


class ExpSumLibrary:
    """Σ_ij W_ij exp((A Bᵀ)_ij) and its gradients over a batch of matrices, computed by `exp_sum.c`.

    Operands are float64 CPU tensors `batch x n x K`, `batch x m x K`, `batch x n x m` (views with
    any batch strides, the last two dimensions contiguous); ``offsets`` are their per-item element
    offsets `items` (int64), so that broadcast copies are never materialised, and ``offsets[3]``
    the order in which to visit the items (those sharing a W together).
    """

    def __init__(self, lib: ctypes.CDLL) -> None:
        lib.qtl_exp_sum_forward.argtypes = [*_COMMON, _PTR, _PTR, _PTR, _INT]
        lib.qtl_exp_sum_forward.restype = _INT
        lib.qtl_exp_sum_forward_lower.argtypes = [*_COMMON, _PTR, _PTR, _PTR, _PTR, _INT]
        lib.qtl_exp_sum_forward_lower.restype = _INT
        lib.qtl_exp_sum_backward.argtypes = [*_COMMON, _PTR, _PTR, _PTR, _PTR, _INT]
        lib.qtl_exp_sum_backward.restype = _INT
        self._lib = lib

    @staticmethod
    def _sizes(a: Tensor, b: Tensor, offsets: tuple[Tensor, Tensor, Tensor, Tensor]) -> list[int]:
        return [offsets[0].numel(), a.shape[-2], b.shape[-2], a.shape[-1]]

    def forward(
        self,
        a: Tensor,
        b: Tensor,
        w: Tensor,
        offsets: tuple[Tensor, Tensor, Tensor, Tensor],
        with_grads: tuple[bool, bool] = (False, False),
        lower: Tensor | None = None,
    ) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """The sums `items`, and where ``with_grads`` asks, G_A `items x n x K` and G_B `items x m x K`.

        G_A[i] = Σ_j W_ij exp(a_i·b_j) b_j and G_B[j] = Σ_i W_ij exp(a_i·b_j) a_i, the gradients of
        the sums for A and B, formed in the same pass as the sums (None where not asked for).
        ``lower`` `items` (bool, n = m): the flagged items summed from the lower triangle with W_ij + W_ji,
        for S = A Bᵀ symmetric (the same sum; their G_A and G_B are the lower form's, see `exp_sum.c`).
        """
        sizes = self._sizes(a, b, offsets)
        items, n, m, k = sizes
        out = a.new_empty(items)
        g_a = a.new_empty(items, n, k) if with_grads[0] else None
        g_b = a.new_empty(items, m, k) if with_grads[1] else None
        if lower is None:
            status = self._lib.qtl_exp_sum_forward(
                _ptr(a), _ptr(b), _ptr(w), *map(_ptr, offsets), *sizes,
                _ptr(out), _ptr(g_a), _ptr(g_b), torch.get_num_threads(),
            )  # fmt: skip
        else:
            flags = lower.to(torch.uint8).contiguous().reshape(-1)
            if flags.numel() != items:
                raise ValueError(f"lower must have one flag per item ({items}), got {flags.numel()}")
            status = self._lib.qtl_exp_sum_forward_lower(
                _ptr(a), _ptr(b), _ptr(w), *map(_ptr, offsets), *sizes, _ptr(flags),
                _ptr(out), _ptr(g_a), _ptr(g_b), torch.get_num_threads(),
            )  # fmt: skip
            if status == 2:
                raise ValueError(f"lower sums need square weights, got n = {n}, m = {m}")
        if status:
            raise MemoryError("the native exp-sum kernel could not allocate its scratch memory")
        return out, g_a, g_b

    def backward(
        self,
        a: Tensor,
        b: Tensor,
        w: Tensor,
        offsets: tuple[Tensor, Tensor, Tensor, Tensor],
        grad: Tensor,
        needs: tuple[bool, bool, bool],
    ) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
        """Gradients for A `items x n x K`, B `items x m x K`, W `items x n x m` (None where not needed).

        ``grad`` `items` (contiguous) is the gradient of the sums.
        """
        sizes = self._sizes(a, b, offsets)
        items, n, m, k = sizes
        grad_a = a.new_empty(items, n, k) if needs[0] else None
        grad_b = a.new_empty(items, m, k) if needs[1] else None
        grad_w = a.new_empty(items, n, m) if needs[2] else None
        status = self._lib.qtl_exp_sum_backward(
            _ptr(a), _ptr(b), _ptr(w), *map(_ptr, offsets), *sizes,
            _ptr(grad), _ptr(grad_a), _ptr(grad_b), _ptr(grad_w), torch.get_num_threads(),
        )  # fmt: skip
        if status:
            raise MemoryError("the native exp-sum kernel could not allocate its scratch memory")
        return grad_a, grad_b, grad_w


def load_exp_sum() -> ExpSumLibrary:
    """The exp-sum kernel built for these sources, flags and CPU; ImportError (saying why) when it cannot load."""
    return load_binding(ExpSumLibrary)


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
