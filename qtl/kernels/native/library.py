"""The compiled exp-sum kernel, loaded through ctypes: forward and backward on float64 CPU tensors."""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import torch  # first: the kernel then shares the libgomp torch has loaded
from torch import Tensor

from qtl.kernels.native.artefact import artefact_path

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

    def __init__(self, path: Path) -> None:
        lib = ctypes.CDLL(str(path))
        lib.qtl_exp_sum_forward.argtypes = [*_COMMON, _PTR, _PTR, _PTR, _INT]
        lib.qtl_exp_sum_forward.restype = _INT
        lib.qtl_exp_sum_forward_lower.argtypes = [*_COMMON, _PTR, _PTR, _PTR, _PTR, _INT]
        lib.qtl_exp_sum_forward_lower.restype = _INT
        lib.qtl_exp_sum_backward.argtypes = [*_COMMON, _PTR, _PTR, _PTR, _PTR, _INT]
        lib.qtl_exp_sum_backward.restype = _INT
        self._lib = lib
        self.path = path

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


Binding = TypeVar("Binding")


@functools.cache
def _open(binding: Callable[[Path], Binding], path: Path) -> Binding:
    return binding(path)


def load_binding(binding: Callable[[Path], Binding]) -> Binding:
    """``binding`` (a ctypes wrapper of some of its symbols) over the library built for these sources, flags and CPU.

    Opened once per (binding, path); an ImportError saying why when the library is missing or lacks the symbols.
    """
    path = artefact_path()
    if not path.is_file():
        raise ImportError(f"{path.name} is not built for these sources and CPU")
    try:
        return _open(binding, path)
    except (OSError, AttributeError) as err:
        raise ImportError(f"{path.name} does not load: {err}") from err


@functools.cache
def binding_once(binding: Callable[[Path], Binding]) -> Binding:
    """:func:`load_binding`, once per process for hot paths (finding the artefact hashes the sources)."""
    return load_binding(binding)


def load_exp_sum() -> ExpSumLibrary:
    """The exp-sum kernel built for these sources, flags and CPU; ImportError (saying why) when it cannot load."""
    return load_binding(ExpSumLibrary)
