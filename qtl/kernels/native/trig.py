"""Angle features and sine squashing at Gaussian inputs by `trig.c`: one compiled call forward, one backward.

The native twins of the fused formulation's :meth:`qtl.features.AngleFeatures.moments` and
:func:`qtl.policies.squash._squash_terms` (PILCO's gTrig and gSat), taken under
``kernels.moments=native`` for float64 CPU operands. Inputs are views whose batch dimensions may be
expanded (per-item offsets, never copies); gradients come back at those shapes and autograd sums
them over the expanded dimensions.
"""

from __future__ import annotations

import ctypes
import functools
import math

import torch  # first: the library then shares the libgomp torch has loaded
from torch import Tensor
from torch.autograd.function import FunctionCtx, once_differentiable

from qtl.kernels.native.exp_sum import item_offsets
from qtl.kernels.native.loader import binding_once, load_binding

_PTR, _INT64 = ctypes.c_void_p, ctypes.c_int64


def _ptr(t: Tensor | None) -> int | None:
    """The address of a tensor's first element (None: a zero gradient)."""
    return None if t is None else t.data_ptr()


class TrigLibrary:
    """The four entry points of `trig.c` (angle features and sine squashing, forward and backward)."""

    def __init__(self, lib: ctypes.CDLL) -> None:
        # items, dim, num, angles, others, mean, cov, off_mean, off_cov
        features = [_INT64] * 3 + [_PTR] * 6
        lib.qtl_trig_features_forward.argtypes = [*features, *[_PTR] * 4]
        lib.qtl_trig_features_backward.argtypes = [*features, *[_PTR] * 6]
        # items, num, bound, mean, cov, off_mean, off_cov
        squash = [_INT64] * 2 + [_PTR] * 5
        lib.qtl_sin_squash_forward.argtypes = [*squash, *[_PTR] * 3]
        lib.qtl_sin_squash_backward.argtypes = [*squash, *[_PTR] * 5]
        for entry in (lib.qtl_trig_features_forward, lib.qtl_trig_features_backward):
            entry.restype = ctypes.c_int
        for entry in (lib.qtl_sin_squash_forward, lib.qtl_sin_squash_backward):
            entry.restype = ctypes.c_int
        self.lib = lib


def load_trig() -> TrigLibrary:
    """The trig kernels built for these sources, flags and CPU; ImportError (saying why) when they cannot load."""
    return load_binding(TrigLibrary)


def applicable(*tensors: Tensor) -> bool:
    """Whether the compiled path takes these operands: all float64 on the CPU."""
    return all(t.dtype == torch.float64 and t.device.type == "cpu" for t in tensors)


@functools.lru_cache(maxsize=64)
def _layout(dim: int, angle_dims: tuple[int, ...]) -> tuple[ctypes.Array, ctypes.Array]:
    """The angle dims and the kept dims of a ``dim``-D state as C int64 arrays (made once)."""
    others = tuple(i for i in range(dim) if i not in set(angle_dims))
    return (ctypes.c_int64 * max(len(angle_dims), 1))(*angle_dims), (ctypes.c_int64 * max(len(others), 1))(*others)


def _rows(t: Tensor) -> Tensor:
    """``t`` when its last two dimensions are row-major contiguous (batch strides free), else a contiguous copy."""
    rows, cols = t.shape[-2:]
    row_stride, col_stride = t.stride()[-2:]
    if (col_stride == 1 or cols == 1) and (row_stride == cols or rows == 1):
        return t
    return t.contiguous()


def _dense(t: Tensor | None) -> Tensor | None:
    """An upstream gradient, contiguous (None stays None: a zero gradient)."""
    return None if t is None else t.contiguous()


class NativeAngleFeatures(torch.autograd.Function):
    """(mean `B x E`, cov `B x E x E`, cross_cov `B x D x E`, gain `B x D x E`) of the angle features, `E = D + K`.

    ``mean`` `B x D` and ``cov`` `B x D x D` share their batch shape `B` (expanded views are fine);
    the twin of the fused branch of :meth:`qtl.features.AngleFeatures.moments`.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: FunctionCtx, mean: Tensor, cov: Tensor, angle_dims: tuple[int, ...], library: TrigLibrary
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        batch, dim = mean.shape[:-1], mean.shape[-1]
        width = dim + len(angle_dims)
        offsets = (item_offsets(mean, batch), item_offsets(cov, batch))
        angles, others = _layout(dim, angle_dims)
        out_mean = mean.new_empty(*batch, width)
        out_cov = mean.new_empty(*batch, width, width)
        cross_cov = mean.new_empty(*batch, dim, width)
        gain = mean.new_empty(*batch, dim, width)
        library.lib.qtl_trig_features_forward(
            math.prod(batch), dim, len(angle_dims), angles, others, _ptr(mean), _ptr(cov), *map(_ptr, offsets),
            _ptr(out_mean), _ptr(out_cov), _ptr(cross_cov), _ptr(gain),
        )  # fmt: skip
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(mean, cov)
        ctx.offsets, ctx.angle_dims, ctx.library = offsets, angle_dims, library
        return out_mean, out_cov, cross_cov, gain

    @staticmethod
    @once_differentiable
    def backward(  # type: ignore[override]
        ctx: FunctionCtx, g_mean: Tensor | None, g_cov: Tensor | None, g_cross: Tensor | None, g_gain: Tensor | None
    ) -> tuple[Tensor | None, ...]:
        mean, cov = ctx.saved_tensors
        batch, dim = mean.shape[:-1], mean.shape[-1]
        angles, others = _layout(dim, ctx.angle_dims)
        grads = [_dense(g) for g in (g_mean, g_cov, g_cross, g_gain)]  # held: the C call reads them
        grad_mean = mean.new_empty(*batch, dim)
        grad_cov = mean.new_empty(*batch, dim, dim)
        ctx.library.lib.qtl_trig_features_backward(
            math.prod(batch), dim, len(ctx.angle_dims), angles, others, _ptr(mean), _ptr(cov), *map(_ptr, ctx.offsets),
            *map(_ptr, grads), _ptr(grad_mean), _ptr(grad_cov),
        )  # fmt: skip
        return grad_mean, grad_cov, None, None


class NativeSinSquash(torch.autograd.Function):
    """(mean `B x F`, symmetrized cov `B x F x F`, slope `B x 1 x F`) of u = u_max (9 sin z + sin 3z)/8.

    ``mean`` `B x F` and ``cov`` `B x F x F` share their batch shape `B` (expanded views are fine),
    ``bound`` `F` (u_max, contiguous, no gradient); the twin of the fused
    :func:`qtl.policies.squash._squash_terms` followed by ``symmetrize`` of its covariance.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: FunctionCtx, mean: Tensor, cov: Tensor, bound: Tensor, library: TrigLibrary
    ) -> tuple[Tensor, Tensor, Tensor]:
        batch, num = mean.shape[:-1], mean.shape[-1]
        offsets = (item_offsets(mean, batch), item_offsets(cov, batch))
        out_mean = mean.new_empty(*batch, num)
        out_cov = mean.new_empty(*batch, num, num)
        slope = mean.new_empty(*batch, 1, num)
        library.lib.qtl_sin_squash_forward(
            math.prod(batch), num, _ptr(bound), _ptr(mean), _ptr(cov), *map(_ptr, offsets),
            _ptr(out_mean), _ptr(out_cov), _ptr(slope),
        )  # fmt: skip
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(mean, cov, bound)
        ctx.offsets, ctx.library = offsets, library
        return out_mean, out_cov, slope

    @staticmethod
    @once_differentiable
    def backward(  # type: ignore[override]
        ctx: FunctionCtx, g_mean: Tensor | None, g_cov: Tensor | None, g_slope: Tensor | None
    ) -> tuple[Tensor | None, ...]:
        mean, cov, bound = ctx.saved_tensors
        batch, num = mean.shape[:-1], mean.shape[-1]
        grads = [_dense(g) for g in (g_mean, g_cov, g_slope)]  # held: the C call reads them
        grad_mean = mean.new_empty(*batch, num)
        grad_cov = mean.new_empty(*batch, num, num)
        ctx.library.lib.qtl_sin_squash_backward(
            math.prod(batch), num, _ptr(bound), _ptr(mean), _ptr(cov), *map(_ptr, ctx.offsets),
            *map(_ptr, grads), _ptr(grad_mean), _ptr(grad_cov),
        )  # fmt: skip
        return grad_mean, grad_cov, None, None


def _common_batch(mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
    """``mean`` `... x D` and ``cov`` `... x D x D` expanded (views) to their common batch shape."""
    if mean.shape[:-1] == cov.shape[:-2]:
        return mean, cov
    batch = torch.broadcast_shapes(mean.shape[:-1], cov.shape[:-2])
    if mean.shape[:-1] != batch:
        mean = mean.expand(*batch, mean.shape[-1])
    if cov.shape[:-2] != batch:
        cov = cov.expand(*batch, *cov.shape[-2:])
    return mean, cov


def angle_feature_moments(
    mean: Tensor, cov: Tensor, angle_dims: tuple[int, ...]
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Mean `... x E`, cov `... x E x E`, cross_cov `... x D x E`, gain `... x D x E` of y = [x_other, sin, cos, …].

    x ~ N(``mean`` `... x D`, ``cov`` `... x D x D`) (float64, CPU; batch shapes broadcast), angles at
    ``angle_dims`` (at least one), `E = D + K`; by :class:`NativeAngleFeatures`.
    """
    mean, cov = _common_batch(mean, cov)
    mean = mean if mean.stride(-1) == 1 or mean.shape[-1] == 1 else mean.contiguous()
    return NativeAngleFeatures.apply(mean, _rows(cov), tuple(angle_dims), binding_once(TrigLibrary))


def sin_squash_terms(mean: Tensor, cov: Tensor, bound: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """E[u] `... x F`, symmetrized cov[u] `... x F x F` and diag E[∂u/∂z] as `... x 1 x F` for z ~ N(mean, cov).

    ``mean`` `... x F`, ``cov`` `... x F x F` (float64, CPU; batch shapes broadcast), ``bound`` `F`
    (u_max, no gradient); by :class:`NativeSinSquash`.
    """
    mean, cov = _common_batch(mean, cov)
    mean = mean if mean.stride(-1) == 1 or mean.shape[-1] == 1 else mean.contiguous()
    return NativeSinSquash.apply(mean, _rows(cov), bound.contiguous(), binding_once(TrigLibrary))

