"""The RBF network policy at a batch of points by `rbf_network.c`: one compiled call forward, one backward.

The native twin of ``qtl.policies.rbf_network._NetworkValues`` (the fused op), taken under
``kernels.moments=native`` for float64 CPU operands: u_pf = Σ_s w_sf m_ps exp(−½ Σ_d (x_pd − c_sd)²/ℓ_fd²),
with the gradients for the points, the centres, the weights and the log-lengthscales from the kept activations.
"""

from __future__ import annotations

import ctypes

import torch  # first: the library then shares the libgomp torch has loaded
from torch import Tensor
from torch.autograd.function import FunctionCtx, once_differentiable

from qtl.kernels.native.loader import binding_once, load_binding

_PTR, _INT64 = ctypes.c_void_p, ctypes.c_int64
# The build's smoke check: relative to the largest reference value (float64; the kernel agrees to ~1e-15).
CHECK_RTOL = 1e-12


def _ptr(t: Tensor | None) -> int | None:
    """The address of a tensor's first element (None: not given, or not wanted)."""
    return None if t is None else t.data_ptr()


class NetworkLibrary:
    """``qtl_rbf_network_forward`` and ``qtl_rbf_network_backward`` of the compiled library, through ctypes."""

    def __init__(self, lib: ctypes.CDLL) -> None:
        # x, c, w, a, mask, m, n, dim, f, u, k
        lib.qtl_rbf_network_forward.argtypes = [*[_PTR] * 5, *[_INT64] * 4, _PTR, _PTR]
        # x, c, w, a, k, g, m, n, dim, f, grad_x, grad_c, grad_w, grad_log_ls
        lib.qtl_rbf_network_backward.argtypes = [*[_PTR] * 6, *[_INT64] * 4, *[_PTR] * 4]
        lib.qtl_rbf_network_forward.restype = ctypes.c_int
        lib.qtl_rbf_network_backward.restype = ctypes.c_int
        self.lib = lib

    def forward(self, x: Tensor, centres: Tensor, weights: Tensor, inv_sq: Tensor, mask: Tensor | None
                ) -> tuple[Tensor, Tensor]:  # fmt: skip
        """u `M x F` and the activations k `F x M x N` (mask applied), for dense float64 CPU operands."""
        (m, dim), (n, f_dim) = x.shape, weights.shape
        values, kern = x.new_empty(m, f_dim), x.new_empty(f_dim, m, n)
        status = self.lib.qtl_rbf_network_forward(
            *map(_ptr, (x, centres, weights, inv_sq, mask)), m, n, dim, f_dim, _ptr(values), _ptr(kern)
        )
        if status:
            raise MemoryError("the native RBF-network kernel could not allocate its scratch memory")
        return values, kern

    def backward(self, x: Tensor, centres: Tensor, weights: Tensor, inv_sq: Tensor, kern: Tensor, grad: Tensor,
                 with_x: bool) -> tuple[Tensor | None, Tensor, Tensor, Tensor]:  # fmt: skip
        """∂ for x `M x D` (None unless ``with_x``), the centres `N x D`, weights `N x F` and log ℓ `F x D`."""
        (m, dim), (n, f_dim) = x.shape, weights.shape
        grad_x = x.new_empty(m, dim) if with_x else None
        grad_c, grad_w, grad_ls = x.new_empty(n, dim), x.new_empty(n, f_dim), x.new_empty(f_dim, dim)
        status = self.lib.qtl_rbf_network_backward(
            *map(_ptr, (x, centres, weights, inv_sq, kern, grad)), m, n, dim, f_dim,
            *map(_ptr, (grad_x, grad_c, grad_w, grad_ls)),
        )  # fmt: skip
        if status:
            raise MemoryError("the native RBF-network kernel could not allocate its scratch memory")
        return grad_x, grad_c, grad_w, grad_ls


def load_network() -> NetworkLibrary:
    """The RBF-network kernel built for these sources, flags and CPU; ImportError (saying why) when it cannot load."""
    return load_binding(NetworkLibrary)


def applicable(*tensors: Tensor | None) -> bool:
    """Whether the compiled path takes these operands: float64 on the CPU (None: an absent mask)."""
    return all(t is None or (t.dtype == torch.float64 and t.device.type == "cpu") for t in tensors)


class NativeNetworkValues(torch.autograd.Function):
    """u `M x F` by `rbf_network.c` for x `M x D`, centres `N x D`, weights `N x F`, log ℓ `F x D`, mask `M x N`|None.

    The gradient flows to x, the centres, the weights and log ℓ (each formed only when needed; ψ's three
    together, in one call). The fused torch twin is ``qtl.policies.rbf_network._NetworkValues``.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: FunctionCtx, x: Tensor, centres: Tensor, weights: Tensor, log_lengthscales: Tensor, mask: Tensor | None,
        library: NetworkLibrary,
    ) -> Tensor:  # fmt: skip
        x, centres, weights = x.contiguous(), centres.contiguous(), weights.contiguous()
        inv_sq = torch.exp(-2.0 * log_lengthscales).contiguous()
        mask = None if mask is None else mask.contiguous()
        values, kern = library.forward(x, centres, weights, inv_sq, mask)
        ctx.save_for_backward(x, centres, weights, inv_sq, kern)
        ctx.library = library
        return values

    @staticmethod
    @once_differentiable
    def backward(ctx: FunctionCtx, grad_out: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        x, centres, weights, inv_sq, kern = ctx.saved_tensors
        need_x, need_c, need_w, need_ls = ctx.needs_input_grad[:4]
        grad_x, grad_c, grad_w, grad_ls = ctx.library.backward(
            x, centres, weights, inv_sq, kern, grad_out.contiguous(), need_x
        )
        return grad_x, grad_c if need_c else None, grad_w if need_w else None, grad_ls if need_ls else None, None, None


def network_values(x: Tensor, centres: Tensor, weights: Tensor, log_lengthscales: Tensor, mask: Tensor | None,
                   library: NetworkLibrary | None = None) -> Tensor:  # fmt: skip
    """u `M x F` by the compiled kernel (operands as in ``NativeNetworkValues``), differentiable."""
    library = library or binding_once(NetworkLibrary)
    return NativeNetworkValues.apply(x, centres, weights, log_lengthscales, mask, library)


def _reference(x: Tensor, centres: Tensor, weights: Tensor, log_lengthscales: Tensor, mask: Tensor | None) -> Tensor:
    """The same u by plain torch operations, point by basis by dimension (autograd gives the gradients)."""
    diff = x[None, :, None, :] - centres[None, None, :, :]  # 1 x M x N x D
    sq = (diff.square() * torch.exp(-2.0 * log_lengthscales)[:, None, None, :]).sum(-1)  # F x M x N
    kern = torch.exp(-0.5 * sq) * (1.0 if mask is None else mask)
    return (kern * weights.mT[:, None, :]).sum(-1).mT


def check_against_torch(library: NetworkLibrary | None = None, error: type[Exception] = RuntimeError) -> None:
    """Values and every gradient of the compiled kernel equal plain torch on a small odd-shaped problem.

    M = 7 points, N = 11 bases, D = 3, F = 2, with a dropout-like mask and without; raises ``error`` (e.g.
    ``build.BuildError``) beyond CHECK_RTOL of the largest value. The fused op is compared by the test suite.
    """
    library = library or load_network()
    gen = torch.Generator().manual_seed(0)
    f64 = torch.float64
    x = torch.randn(7, 3, generator=gen, dtype=f64).requires_grad_()
    psi = [torch.randn(11, 3, generator=gen, dtype=f64), torch.randn(11, 2, generator=gen, dtype=f64),
           0.3 * torch.randn(2, 3, generator=gen, dtype=f64)]  # fmt: skip
    psi = [t.requires_grad_() for t in psi]
    probe = torch.randn(7, 2, generator=gen, dtype=f64)
    for mask in (None, (torch.rand(7, 11, generator=gen, dtype=f64) >= 0.3).to(f64) / 0.7):
        results = []
        for value in (network_values(x, *psi, mask, library=library), _reference(x, *psi, mask)):
            results.append((value, *torch.autograd.grad((value * probe).sum(), (x, *psi))))
        for got, want in zip(*results, strict=True):
            err, scale = (got - want).abs().max().item(), want.abs().max().item()
            if got.shape != want.shape or not err <= CHECK_RTOL * scale:
                raise error(f"the compiled RBF-network kernel disagrees with torch (max error {err:.3g})")
