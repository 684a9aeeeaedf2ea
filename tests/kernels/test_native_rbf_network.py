"""The native RBF network (`rbf_network.c`) against its torch twins: values, every gradient, dropout masks, rollouts."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from qtl.kernels.engine import Engine
from qtl.kernels.native import rbf_network as native_network
from qtl.kernels.native.rbf_network import NativeNetworkValues, check_against_torch, load_network
from qtl.policies import RBFNetwork
from qtl.policies.rbf_network import _NetworkValues

DTYPE = torch.float64
# The compiled op and the torch ones differ only in the order of floating-point operations.
RTOL = 1e-12


@pytest.fixture(scope="module")
def library(built):
    """The compiled library (built once for the module)."""
    return load_network()


def make_problem(m: int, n: int, dim: int, f_dim: int, seed: int, rate: float) -> tuple[Tensor, ...]:
    """Points `M x D`, centres `N x D`, weights `N x F`, log ℓ `F x D` and a mask `M x N` (or None)."""
    gen = torch.Generator().manual_seed(seed)
    x = 1.5 * torch.randn(m, dim, generator=gen, dtype=DTYPE)
    centres = 1.5 * torch.randn(n, dim, generator=gen, dtype=DTYPE)
    weights = torch.randn(n, f_dim, generator=gen, dtype=DTYPE)
    log_ls = 0.4 * torch.randn(f_dim, dim, generator=gen, dtype=DTYPE)
    mask = None
    if rate:
        mask = (torch.rand(m, n, generator=gen, dtype=DTYPE) >= rate).to(DTYPE) / (1.0 - rate)
    return x, centres, weights, log_ls, mask


@pytest.mark.parametrize(("m", "n", "dim", "f_dim", "rate"),
                         [(400, 200, 5, 1, 0.25), (13, 37, 3, 2, 0.0), (1, 1, 1, 1, 0.0), (9, 70, 6, 3, 0.5)])
def test_values_and_gradients_equal_the_fused_op_and_plain_torch(library, m, n, dim, f_dim, rate):
    """u and ∂ for x, c, w, log ℓ: the compiled op, the fused torch op and the plain formula, to RTOL."""
    x, *psi, mask = make_problem(m, n, dim, f_dim, seed=m + n, rate=rate)
    leaves = [t.clone().requires_grad_() for t in (x, *psi)]
    probe = torch.randn(m, f_dim, generator=torch.Generator().manual_seed(1), dtype=DTYPE)
    results = []
    for op in (lambda *a: NativeNetworkValues.apply(*a, library), _NetworkValues.apply, native_network._reference):
        value = op(*leaves, mask)
        results.append((value, *torch.autograd.grad((value * probe).sum(), leaves)))
    for native, fused, plain in zip(*results, strict=True):
        scale = plain.abs().max().item()
        torch.testing.assert_close(native, plain, rtol=RTOL, atol=RTOL * scale)
        torch.testing.assert_close(fused, plain, rtol=1e-10, atol=1e-10 * scale)


@pytest.mark.parametrize("masked", [False, True])
def test_gradcheck(library, masked):
    """Finite differences (float64) of the compiled op for x and ψ, with and without a mask."""
    x, *psi, mask = make_problem(6, 8, 3, 2, seed=3, rate=0.3 if masked else 0.0)
    leaves = tuple(t.requires_grad_() for t in (x, *psi))
    assert torch.autograd.gradcheck(lambda *a: NativeNetworkValues.apply(*a, mask, library), leaves)


def test_only_the_wanted_gradients_come_back(library):
    """Points without gradient (a rollout's start) and frozen centres: None for them, the rest as torch's."""
    x, centres, weights, log_ls, mask = make_problem(11, 17, 4, 1, seed=5, rate=0.2)
    weights.requires_grad_()
    value = NativeNetworkValues.apply(x, centres, weights, log_ls, mask, library)
    (grad_w,) = torch.autograd.grad(value.sum(), weights)
    want = torch.autograd.grad(native_network._reference(x, centres, weights, log_ls, mask).sum(), weights)[0]
    torch.testing.assert_close(grad_w, want, rtol=RTOL, atol=RTOL)
    assert value.grad_fn.next_functions[0][0] is None  # x: no path back


def test_the_build_check_passes_and_catches_a_wrong_kernel(library):
    check_against_torch(library)

    class Wrong:
        def forward(self, *args):
            values, kern = library.forward(*args)
            return values * (1 + 1e-9), kern

        def backward(self, *args):
            return library.backward(*args)

    with pytest.raises(ValueError, match="disagrees with torch"):
        check_against_torch(Wrong(), error=ValueError)


@pytest.mark.parametrize("rate", [0.0, 0.25])
def test_the_network_takes_the_compiled_op_under_native_and_the_same_masks(built, rate):
    """RBFNetwork.forward under kernels.moments=native: the compiled op in the graph, the fused op's values."""
    gen = torch.Generator().manual_seed(7)
    net = RBFNetwork(torch.randn(30, 5, generator=gen, dtype=DTYPE), torch.randn(30, 1, generator=gen, dtype=DTYPE),
                     torch.full((1, 5), 0.8, dtype=DTYPE))
    x = torch.randn(2, 50, 5, generator=gen, dtype=DTYPE)
    results = []
    for form in ("auto", "fused"):
        net.set_dropout(rate, torch.Generator().manual_seed(8))
        actions = net(x, Engine(moments="native", network=form))
        results.append((actions, *torch.autograd.grad(actions.sum(), list(net.parameters()))))
        names = actions.grad_fn.name() + " " + actions.grad_fn.next_functions[0][0].name()
        assert ("NativeNetworkValuesBackward" in names) == (form == "auto")
    for native, fused in zip(*results, strict=True):
        torch.testing.assert_close(native, fused, rtol=1e-10, atol=1e-12)
    # float32 points: the fused torch op
    net32 = RBFNetwork(*(p.detach().float() for p in (net.centres, net.weights)), torch.full((1, 5), 0.8))
    assert "NativeNetworkValues" not in net32(x.float(), Engine(moments="native")).grad_fn.next_functions[0][0].name()
