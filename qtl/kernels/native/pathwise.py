"""The native pathwise-function values (`pathwise.c`): f and ∂f/∂z̃ in one compiled call, as an autograd op.

The twin of ``qtl.propagation.pathwise._PathValues`` for float64 or float32 CPU operands (one C body compiled
in both precisions; float32 is what ``propagation.path_dtype=float32`` evaluates in): for each output e and
particle p, f_p(z̃) = Σ_l W_pl cos(ω̃_lᵀ z̃ + b_l) + Σ_i α² exp(−½|z̃ − x̃_i|²) v_pi (inputs over the
lengthscales), with its gradient for z̃ formed in the same pass and kept for backward.
"""

from __future__ import annotations

import ctypes
import functools
import math

import torch  # first: the library then shares the libgomp torch has loaded
from torch import Tensor
from torch.autograd.function import FunctionCtx, once_differentiable

from qtl.kernels.native.loader import binding_once, load_binding

_PTR, _INT64, _INT = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
# The smoke check's tolerance (relative to the largest reference value, float64).
CHECK_RTOL = 1e-12
# The same in float32, against the float32 torch twin: each of the ~L + n terms is within a few ulp
# (2⁻²⁴ ≈ 6e-8) of its value times (1 + |angle|), and the angles are O(1) here.
CHECK_RTOL_F32 = 1e-5
# The compiled entry point per operand dtype.
ENTRY_POINTS = {torch.float64: "qtl_path_values", torch.float32: "qtl_path_values_f32"}


class PathValuesLibrary:
    """``qtl_path_values`` (float64) and ``qtl_path_values_f32`` (float32) of the compiled library, through ctypes."""

    def __init__(self, lib: ctypes.CDLL) -> None:
        self._entries = {}
        for dtype, name in ENTRY_POINTS.items():
            entry = getattr(lib, name)
            # z, x, sf2, omega, phase, w, v, offsets, row_strides, items, rows, n, L, D, f, grad, threads
            entry.argtypes = [*[_PTR] * 9, *[_INT64] * 5, _PTR, _PTR, _INT]
            entry.restype = _INT
            self._entries[dtype] = entry
        self._lib = lib

    def values(
        self,
        z: Tensor,
        data: Tensor,
        signal_variance: Tensor,
        frequencies: Tensor,
        phases: Tensor,
        weights: Tensor,
        update: Tensor,
        with_grad: bool,
    ) -> tuple[Tensor, Tensor | None]:
        """f `*batch x E x P` and, with ``with_grad``, ∂f/∂z̃ `*batch x E x P x D` (else None).

        z `... x E x P x D`, data `... x E x n x D`, signal_variance α² `... x E`, frequencies
        `... x E x L x D`, phases `... x E x L`, weights `... x E x P x L`, update `... x E x P x n`:
        leading dimensions (E and P included) broadcast, and are never copied per item. All operands
        float64, or all float32 (the float32 kernel); the results have their dtype.
        """
        batch = torch.broadcast_shapes(
            z.shape[:-2], data.shape[:-2], signal_variance.shape, frequencies.shape[:-2], phases.shape[:-1],
            weights.shape[:-2], update.shape[:-2],
        )  # fmt: skip
        rows = torch.broadcast_shapes(z.shape[-2:-1], weights.shape[-2:-1], update.shape[-2:-1])[0]
        n, num_features, dim = data.shape[-2], frequencies.shape[-2], z.shape[-1]
        z, data, frequencies, phases, weights, update, signal_variance = (
            _unit_stride(t).expand(*batch, *inner)
            for t, inner in (
                (z, (rows, dim)), (data, (n, dim)), (frequencies, (num_features, dim)), (phases, (num_features,)),
                (weights, (rows, num_features)), (update, (rows, n)), (signal_variance, ()),
            )
        )  # fmt: skip
        operands = (z, data, signal_variance, frequencies, phases, weights, update)
        offsets = _offset_table(tuple(batch), tuple(t.stride()[: len(batch)] for t in operands))
        row_strides = _row_strides(tuple(t.stride(-2) for t in (z, data, frequencies, weights, update)))
        items = math.prod(batch)
        value = z.new_empty(*batch, rows)
        grad = z.new_empty(*batch, rows, dim) if with_grad else None
        status = self._entries[z.dtype](
            *(t.data_ptr() for t in operands), offsets.data_ptr(), row_strides.data_ptr(),
            items, rows, n, num_features, dim, value.data_ptr(), None if grad is None else grad.data_ptr(),
            torch.get_num_threads(),
        )  # fmt: skip
        if status:
            raise MemoryError("the native pathwise kernel could not allocate its scratch memory")
        return value, grad


def _unit_stride(t: Tensor) -> Tensor:
    """``t``, or a contiguous copy when its last dimension is not unit-stride."""
    return t if t.dim() == 0 or t.shape[-1] == 1 or t.stride(-1) == 1 else t.contiguous()


@functools.lru_cache(maxsize=256)
def _offset_table(batch: tuple[int, ...], strides: tuple[tuple[int, ...], ...]) -> Tensor:
    """Every operand's per-item element offsets `7 x items` (int64; cached: a rollout repeats its shapes)."""
    table = torch.zeros(len(strides), *batch, dtype=torch.int64)
    for dim, size in enumerate(batch):
        index = torch.arange(size, dtype=torch.int64).view(size, *(1,) * (len(batch) - dim - 1))
        table += torch.tensor([s[dim] for s in strides], dtype=torch.int64).view(-1, *(1,) * len(batch)) * index
    return table.reshape(len(strides), -1).contiguous()


@functools.lru_cache(maxsize=256)
def _row_strides(strides: tuple[int, ...]) -> Tensor:
    """The row strides of z, data, frequencies, weights and update as an int64 tensor `5` (cached)."""
    return torch.tensor(strides, dtype=torch.int64)


class NativePathValues(torch.autograd.Function):
    """f `... x E x P` by `pathwise.c`; the forward pass also forms ∂f/∂z̃ and keeps only that (for ``z``).

    Operands as :meth:`PathValuesLibrary.values`; ``grad_enabled`` is ``torch.is_grad_enabled()`` at
    the call. The gradient flows to ``z`` only. The reference twin is ``qtl.propagation.pathwise._PathValues``.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: FunctionCtx,
        z: Tensor,
        data: Tensor,
        signal_variance: Tensor,
        frequencies: Tensor,
        phases: Tensor,
        weights: Tensor,
        update: Tensor,
        library: PathValuesLibrary,
        grad_enabled: bool,
    ) -> Tensor:
        with_grad = grad_enabled and ctx.needs_input_grad[0]
        value, grad = library.values(z, data, signal_variance, frequencies, phases, weights, update, with_grad)
        if with_grad:
            ctx.save_for_backward(grad)
        return value

    @staticmethod
    @once_differentiable
    def backward(ctx: FunctionCtx, grad_out: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        (grad,) = ctx.saved_tensors
        return grad * grad_out[..., None], *(None,) * 8


def native_fits(*tensors: Tensor) -> bool:
    """Whether the native path values take these operands: on the CPU, all float64 or all float32."""
    dtype = tensors[0].dtype
    return dtype in ENTRY_POINTS and all(t.device.type == "cpu" and t.dtype == dtype for t in tensors)


def path_values(
    z: Tensor,
    data: Tensor,
    signal_variance: Tensor,
    frequencies: Tensor,
    phases: Tensor,
    weights: Tensor,
    update: Tensor,
    library: PathValuesLibrary | None = None,
) -> Tensor:
    """f `... x E x P` at ``z`` `... x E x P x D` by the compiled kernel (operands as in ``PathValuesLibrary``)."""
    library = library or binding_once(PathValuesLibrary)
    return NativePathValues.apply(
        z, data, signal_variance, frequencies, phases, weights, update, library, torch.is_grad_enabled()
    )


def load_path_values() -> PathValuesLibrary:
    """The pathwise kernel built for these sources, flags and CPU; ImportError (saying why) when it cannot load."""
    return load_binding(PathValuesLibrary)


def _reference(
    z: Tensor, data: Tensor, signal_variance: Tensor, frequencies: Tensor, phases: Tensor, weights: Tensor,
    update: Tensor,
) -> Tensor:  # fmt: skip
    """The same f by plain torch operations (autograd gives ∂f/∂z̃): `... x E x P`."""
    sq = (z[..., :, None, :] - data[..., None, :, :]).square().sum(-1)  # ... x E x P x n
    fitted = (signal_variance[..., None, None] * torch.exp(-0.5 * sq) * update).sum(-1)
    angle = z @ frequencies.mT + phases[..., None, :]  # ... x E x P x L
    return fitted + (torch.cos(angle) * weights).sum(-1)


def check_against_torch(library: PathValuesLibrary | None = None, error: type[Exception] = RuntimeError) -> None:
    """Values and ∂f/∂z̃ of the compiled kernel equal plain torch on a small odd-shaped problem.

    z `2 x 3 x 5 x 3` (restarts x E x P x D) against model operands `3 x ...` (n = 7, L = 9) broadcast
    over the restarts, with the update broadcast over the particles too; raises ``error`` (e.g.
    ``build.BuildError``; a RuntimeError by default) when they differ beyond CHECK_RTOL of the largest value.
    ``qtl.propagation.pathwise._PathValues`` (a layer above) is compared with it by the test suite.
    Checked in float64 (CHECK_RTOL) and in float32 (the float32 kernel against float32 torch, CHECK_RTOL_F32).
    """
    library = library or load_path_values()
    gen = torch.Generator().manual_seed(0)
    f64 = torch.float64
    z = 0.7 * torch.randn(2, 3, 5, 3, generator=gen, dtype=f64)
    data = torch.randn(3, 7, 3, generator=gen, dtype=f64)
    signal_variance = 0.5 + torch.rand(3, generator=gen, dtype=f64)
    frequencies = torch.randn(3, 9, 3, generator=gen, dtype=f64)
    phases = 2 * math.pi * torch.rand(3, 9, generator=gen, dtype=f64)
    weights = torch.randn(3, 5, 9, generator=gen, dtype=f64)
    update = torch.randn(3, 1, 7, generator=gen, dtype=f64)
    probe = torch.randn(2, 3, 5, generator=gen, dtype=f64)
    for dtype, rtol in ((f64, CHECK_RTOL), (torch.float32, CHECK_RTOL_F32)):
        point = z.to(dtype).requires_grad_()
        operands = tuple(t.to(dtype) for t in (data, signal_variance, frequencies, phases, weights, update))
        results = []
        for value in (path_values(point, *operands, library=library), _reference(point, *operands)):
            results.append((value, *torch.autograd.grad((value * probe.to(dtype)).sum(), point)))
        for got, want in zip(*results, strict=True):
            err, scale = (got - want).abs().max().item(), want.abs().max().item()
            if got.shape != want.shape or got.dtype != dtype or not err <= rtol * scale:
                raise error(f"the compiled pathwise kernel disagrees with torch in {dtype} (max error {err:.3g})")
