"""The native SE-kernel moments (`se_moments.c`): one compiled call forward, one backward, as an autograd op.

The twin of ``SEKernelMoments._fused_call`` (:mod:`qtl.kernels.moments`) for float64 CPU operands:
mean, covariance (without the model variance diag(α²), which the caller adds) and gain of
f_a(x) = Σ_i β_ai k_a(x_i, x) at x ~ N(μ, Σ), with the hand-derived adjoint of the whole formula.
A batch item whose B_a or R_ab is not positive-definite is flagged by the library (its outputs and
gradients NaN) and reported as :func:`qtl.gaussian.failed_elements` says: raised, or marked inside
:func:`qtl.gaussian.element_failures`.
"""

from __future__ import annotations

import ctypes
import functools
import math

import torch  # first: the library then shares the libgomp torch has loaded
from torch import Tensor
from torch.autograd.function import FunctionCtx, once_differentiable

from qtl.gaussian import batch_shapes, failed_elements
from qtl.kernels.native.loader import binding_once, load_binding

_PTR, _INT64, _INT = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
_PTRS = ctypes.POINTER(ctypes.c_void_p)
_INTS = ctypes.POINTER(ctypes.c_int64)
# Trailing (per-item) dimensions of mean, cov, inputs, beta, inv_ls, log_sf2, weights.
_INNER = (1, 2, 2, 2, 2, 1, 3)
_NUM_OPERANDS = len(_INNER)
_STATUS_NOT_PD = 2
_STATUS_ITEMS_FAILED = 3  # some items flagged as failed (their outputs NaN); the others computed
# Below this many n x n exp-sum entries (items x pairs x n²) a call runs on one thread: a parallel region
# costs more than it saves there (e.g. the RBF policy's n = 50), and the sums are the same for any thread count.
_PARALLEL_ENTRIES = 1 << 15

# The (shape, strides) of each operand: what the library's batch arguments depend on.
Layout = tuple[tuple[torch.Size, tuple[int, ...]], ...]


class SEMomentsLibrary:
    """``qtl_se_moments_forward`` and ``qtl_se_moments_backward`` of the compiled library, through ctypes."""

    def __init__(self, lib: ctypes.CDLL) -> None:
        # operand, ndim, batch, strides, n, d, e
        common = [_PTRS, _INT64, _INTS, _INTS, _INT64, _INT64, _INT64]
        lib.qtl_se_moments_forward.argtypes = [*common, _PTR, _PTR, _PTR, _PTR, _PTR, _INT, _INT, _INT]
        lib.qtl_se_moments_forward.restype = _INT
        lib.qtl_se_moments_backward.argtypes = [*common, _PTR, _PTR, _INT, _PTRS, _INTS, _PTRS, _INTS, _INT]
        lib.qtl_se_moments_backward.restype = _INT
        self._lib = lib

    def forward(
        self,
        operands: tuple[Tensor, ...],
        batch: torch.Size,
        with_grads: bool,
        lower_pairs: bool = True,
        layout: Layout | None = None,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, ctypes.Array | None]:
        """Mean `*batch x E`, cov `*batch x E x E` (no model variance), gain `*batch x D x E`, the work buffer, flags.

        ``operands`` (mean, cov, inputs, beta, inv_ls, log_sf2, weights) are contiguous in their trailing
        dimensions and broadcast to ``batch``; ``with_grads``: the work buffer also keeps the exp sums'
        operand gradients G_A, G_B for the backward pass. ``lower_pairs``: the a = b pairs' exp sums from
        their lower triangles (S_aa is symmetric: E of the E(E+1)/2 sums at half cost); False: every pair's
        full n x n sum (the form before; benchmarks and tests). The flags (`items` bytes, or None where no item
        failed) are 1 for the items whose B_a or R_ab is not positive-definite (their outputs NaN), else 0.
        ``layout``: the operands' (shape, strides) (:func:`_layout`), where the caller has them already.
        """
        inputs, beta = operands[2], operands[3]
        n, d, e = inputs.shape[-2], inputs.shape[-1], beta.shape[-2]
        items, pairs = math.prod(batch), e * (e + 1) // 2
        mean = operands[0]
        out_mean = mean.new_empty(*batch, e)
        out_cov = mean.new_empty(*batch, e, e)
        gain = mean.new_empty(*batch, d, e)
        # the sums `items x P`, the means `items x E`, and with_grads G_A, G_B `items x P x n x (D + 2)` each
        work = mean.new_empty(items * (pairs + e + (2 * pairs * n * (d + 2) if with_grads else 0)))
        flags = (ctypes.c_ubyte * max(items, 1))()  # ctypes, not a tensor: no dispatched op where none fails
        status = self._lib.qtl_se_moments_forward(
            _pointers(operands), *_batch_args(layout or _layout(operands), batch), n, d, e,
            out_mean.data_ptr(), out_cov.data_ptr(), gain.data_ptr(), work.data_ptr(), ctypes.addressof(flags),
            int(with_grads), int(lower_pairs), _threads(items * pairs * n * n),
        )  # fmt: skip
        if status == _STATUS_ITEMS_FAILED:
            return out_mean, out_cov, gain, work, flags
        _raise_for(status)
        return out_mean, out_cov, gain, work, None

    def backward(
        self,
        operands: tuple[Tensor, ...],
        batch: torch.Size,
        work: Tensor,
        failed: ctypes.Array | None,
        fused: bool,
        grad_outputs: tuple[Tensor | None, Tensor | None, Tensor | None],
        needs: tuple[bool, ...],
    ) -> list[Tensor | None]:
        """Gradients of the 7 operands (their own shapes; None where ``needs`` says not), given those of the outputs.

        ``failed``: the forward pass's flags where any item failed (its gradients NaN), else None.
        """
        grads = [torch.zeros(t.shape, dtype=t.dtype) if need else None for t, need in zip(operands, needs, strict=True)]
        layout = _layout(operands)
        out_layout = tuple(None if g is None else g.stride() for g in grad_outputs)
        out_strides, grad_strides = _grad_strides(layout, batch, needs, out_layout)
        n, d, e = _sizes(operands)
        status = self._lib.qtl_se_moments_backward(
            _pointers(operands), *_batch_args(layout, batch), n, d, e,
            work.data_ptr(), None if failed is None else ctypes.addressof(failed), int(fused),
            _pointers(grad_outputs), out_strides, _pointers(grads), grad_strides,
            _threads(math.prod(batch) * (e * (e + 1) // 2) * n * n),
        )  # fmt: skip
        _raise_for(status)
        return grads


def _sizes(operands: tuple[Tensor, ...]) -> tuple[int, int, int]:
    """n, D, E of the operands."""
    inputs, beta = operands[2], operands[3]
    return inputs.shape[-2], inputs.shape[-1], beta.shape[-2]


def _raise_for(status: int) -> None:
    """The error a non-zero status of the library stands for."""
    if status == _STATUS_NOT_PD:
        raise torch.linalg.LinAlgError("the native SE-kernel moments: a B_a or R_ab is not positive-definite")
    if status:
        raise MemoryError("the native SE-kernel moments could not allocate their scratch memory")


def _pointers(tensors: tuple[Tensor | None, ...] | list[Tensor | None]) -> ctypes.Array:
    """The tensors' data pointers (NULL for None), as a C array."""
    return (ctypes.c_void_p * len(tensors))(*(None if t is None else t.data_ptr() for t in tensors))


def _int64s(values: list[int]) -> ctypes.Array:
    """``values`` as a C int64 array."""
    return (ctypes.c_int64 * max(1, len(values)))(*values)


def _threads(entries: int) -> int:
    """The threads of a call whose exp sums have ``entries`` n x n terms: torch's, or one for a small call."""
    return torch.get_num_threads() if entries >= _PARALLEL_ENTRIES else 1


def _aligned_strides(shape: torch.Size, strides: tuple[int, ...], inner: int, ndim: int) -> tuple[int, ...]:
    """The strides of a tensor's leading dimensions (all but ``inner`` trailing ones) aligned right to ``ndim`` batch
    dimensions: 0 where it lacks the dimension or has size 1 (broadcast); then nothing of the inner ones."""
    lead = len(shape) - inner
    lead_strides = (0 if size == 1 else stride for size, stride in zip(shape[:lead], strides[:lead], strict=True))
    return (0,) * (ndim - lead) + tuple(lead_strides)


def _dense_strides(shape: torch.Size) -> tuple[int, ...]:
    """The strides of a contiguous tensor of ``shape``."""
    strides, step = [], 1
    for size in reversed(shape):
        strides.append(step)
        step *= size
    return tuple(reversed(strides))


def _layout(operands: tuple[Tensor, ...]) -> Layout:
    """Each operand's (shape, strides): the key of the cached batch arguments."""
    return tuple((t.shape, t.stride()) for t in operands)


@functools.lru_cache(maxsize=256)
def _operand_batch(layout: Layout) -> torch.Size:
    """The broadcast batch shape of the operands of ``layout`` (all but their trailing dimensions), cached."""
    return batch_shapes(*(shape[: len(shape) - inner] for (shape, _), inner in zip(layout, _INNER, strict=True)))


@functools.lru_cache(maxsize=256)
def _batch_args(layout: Layout, batch: torch.Size) -> tuple[int, ctypes.Array, ctypes.Array]:
    """ndim, the batch sizes and every operand's batch strides (`7 x ndim`), as the library takes them (read only).

    Cached by the operands' shapes and strides: the C arrays are made once per layout, not per call.
    """
    ndim = len(batch)
    strides = [
        s for (shape, st), inner in zip(layout, _INNER, strict=True) for s in _aligned_strides(shape, st, inner, ndim)
    ]
    return ndim, _int64s(list(batch)), _int64s(strides)


@functools.lru_cache(maxsize=256)
def _grad_strides(
    layout: Layout, batch: torch.Size, needs: tuple[bool, ...], out_layout: tuple[tuple[int, ...] | None, ...]
) -> tuple[ctypes.Array, ctypes.Array]:
    """The output gradients' strides (`3 x (ndim + 2)`, their own) and the operand gradients' batch strides
    (`7 x ndim`: dense buffers of the operands' shapes where ``needs`` says, else the operands'), as C arrays."""
    ndim = len(batch)
    out_strides: list[int] = []
    for strides, inner in zip(out_layout, (1, 2, 2), strict=True):  # shapes `*batch x ...`: strides as they are
        out_strides += [*((0,) * (ndim + inner) if strides is None else strides), *(0,) * (2 - inner)]
    grad_strides = [
        s
        for (shape, strides), inner, need in zip(layout, _INNER, needs, strict=True)
        for s in _aligned_strides(shape, _dense_strides(shape) if need else strides, inner, ndim)
    ]
    return _int64s(out_strides), _int64s(grad_strides)


def _trailing_contiguous(t: Tensor, inner: int) -> Tensor:
    """``t``, or a contiguous copy when its ``inner`` trailing dimensions are not laid out row-major."""
    if t.is_contiguous():
        return t
    expected = 1
    for size, stride in zip(reversed(t.shape[t.dim() - inner :]), reversed(t.stride()[t.dim() - inner :]), strict=True):
        if size != 1 and stride != expected:
            return t.contiguous()
        expected *= size
    return t


def load_se_moments() -> SEMomentsLibrary:
    """The SE-moment kernels built for these sources, flags and CPU; ImportError (saying why) when they cannot load."""
    return load_binding(SEMomentsLibrary)


class NativeSEKernelMoments(torch.autograd.Function):
    """Mean `... x E`, covariance `... x E x E` (without diag(α²)) and gain `... x D x E` by `se_moments.c`.

    Operands: mean `... x D`, cov `... x D x D`, inputs `... x n x D`, beta `... x E x n`, inv_ls
    `... x E x D` (1/ℓ), log_sf2 `... x E` (log α²), weights `... x P x n x n` (P = E(E+1)/2, triu
    order); leading dimensions broadcast, and the gradients of broadcast operands are summed in C.
    ``grad_enabled`` is ``torch.is_grad_enabled()`` at the call. When an operand other than the
    weights needs a gradient and the weights do not (the GP dynamics), the forward pass keeps the
    exp sums' operand gradients, so backward has no n x n pass; otherwise backward recomputes.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: FunctionCtx,
        mean: Tensor,
        cov: Tensor,
        inputs: Tensor,
        beta: Tensor,
        inv_ls: Tensor,
        log_sf2: Tensor,
        weights: Tensor,
        library: SEMomentsLibrary,
        grad_enabled: bool,
        lower_pairs: bool,
    ) -> tuple[Tensor, Tensor, Tensor]:
        operands = tuple(
            _trailing_contiguous(t, inner)
            for t, inner in zip((mean, cov, inputs, beta, inv_ls, log_sf2, weights), _INNER, strict=True)
        )
        layout = _layout(operands)
        batch = _operand_batch(layout)
        needs = tuple(ctx.needs_input_grad[:_NUM_OPERANDS]) if grad_enabled else (False,) * _NUM_OPERANDS
        need_ops = any(needs[i] for i in (0, 1, 2, 4, 5))  # all but beta enter the exp sums' operands
        ctx.fused = need_ops and not needs[6]
        out_mean, out_cov, gain, work, flags = library.forward(operands, batch, ctx.fused, lower_pairs, layout)
        if flags is not None:  # raises outside qtl.gaussian.element_failures
            failed = torch.frombuffer(flags, dtype=torch.uint8)[: math.prod(batch)].view(batch).bool()
            failed_elements(failed, what="the native SE-kernel moments (a B_a or R_ab)")
        if any(needs):
            ctx.save_for_backward(*operands)
            ctx.work, ctx.batch, ctx.library, ctx.failed = work, batch, library, flags
        ctx.set_materialize_grads(False)
        return out_mean, out_cov, gain

    @staticmethod
    @once_differentiable
    def backward(  # type: ignore[override]
        ctx: FunctionCtx, grad_mean: Tensor | None, grad_cov: Tensor | None, grad_gain: Tensor | None
    ) -> tuple[Tensor | None, ...]:
        operands = ctx.saved_tensors
        needs = tuple(ctx.needs_input_grad[:_NUM_OPERANDS])
        grads = ctx.library.backward(operands, ctx.batch, ctx.work, ctx.failed, ctx.fused,
                                     (grad_mean, grad_cov, grad_gain), needs)
        return *grads, None, None, None


def native_fits(*tensors: Tensor) -> bool:
    """Whether the native moments take these operands: all float64 on the CPU."""
    return all(t.device.type == "cpu" and t.dtype == torch.float64 for t in tensors)


def se_kernel_moments(
    mean: Tensor,
    cov: Tensor,
    inputs: Tensor,
    beta: Tensor,
    inv_ls: Tensor,
    log_sf2: Tensor,
    weights: Tensor,
    library: SEMomentsLibrary | None = None,
    lower_pairs: bool = True,
) -> tuple[Tensor, Tensor, Tensor]:
    """Mean `... x E`, cov `... x E x E` (no model variance) and gain `... x D x E` by the compiled kernel.

    ``lower_pairs``: as in :meth:`SEMomentsLibrary.forward` (``Engine.lower_pairs``).
    """
    library = library or binding_once(SEMomentsLibrary)
    return NativeSEKernelMoments.apply(
        mean, cov, inputs, beta, inv_ls, log_sf2, weights, library, torch.is_grad_enabled(), lower_pairs
    )
