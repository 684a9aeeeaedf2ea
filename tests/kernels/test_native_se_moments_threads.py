"""The native SE-kernel moments' item-parallel paths and thread choice: the same bits for any thread count."""

from __future__ import annotations

import pytest
import torch

from qtl.kernels.native import se_moments
from qtl.kernels.native.se_moments import load_se_moments
from tests.kernels.test_native_se_moments import (
    FUSED,
    NATIVE,
    SHAPES,
    assert_native_equals_fused,
    make_problem,
    outputs_and_grads,
)


@pytest.fixture(scope="module")
def library(built):
    """The compiled library (built once for the module)."""
    return load_se_moments()


@pytest.fixture
def every_call_parallel(monkeypatch):
    """Every call takes torch's thread count, however small (the item-parallel paths run wherever they may)."""
    monkeypatch.setattr(se_moments, "_PARALLEL_ENTRIES", 0)


def _with_threads(threads: int, leaves, k_inv, probes, engine=NATIVE):
    """``outputs_and_grads`` under ``threads`` torch threads (restored after)."""
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return outputs_and_grads(leaves, k_inv, engine, probes)
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("dynamics", [False, True], ids=["all-grads", "mean-cov-grads"])
@pytest.mark.parametrize(("num_out", "dim", "num", "state_batch", "const_batch"), SHAPES)
def test_outputs_and_gradients_do_not_depend_on_the_thread_count(
    library, every_call_parallel, num_out, dim, num, state_batch, const_batch, dynamics
):
    # Item-parallel forward always; item-parallel adjoint where no wanted gradient is broadcast (the dynamics case
    # with a state batch): bit for bit the serial results.
    leaves, k_inv = make_problem(num_out, dim, num, state_batch, const_batch, seed=3)
    if dynamics:
        for name in ("inputs", "beta", "lengthscales", "signal_variance"):
            leaves[name].requires_grad_(False)
    gen = torch.Generator().manual_seed(5)
    shapes = [o.shape for o in outputs_and_grads(leaves, k_inv, FUSED, None)[0]]
    probes = [torch.randn(s, generator=gen, dtype=torch.float64) for s in shapes]
    one_out, one_grads = _with_threads(1, leaves, k_inv, probes)
    two_out, two_grads = _with_threads(2, leaves, k_inv, probes)
    for one, two in zip([*one_out, *one_grads], [*two_out, *two_grads], strict=True):
        assert (one is None and two is None) or torch.equal(one, two)


@pytest.mark.parametrize(("num_out", "dim", "num", "state_batch", "const_batch"), SHAPES)
def test_item_parallel_paths_equal_the_fused_formulation(
    library, every_call_parallel, num_out, dim, num, state_batch, const_batch
):
    leaves, k_inv = make_problem(num_out, dim, num, state_batch, const_batch, seed=4)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        assert_native_equals_fused(leaves, k_inv)
    finally:
        torch.set_num_threads(before)


def test_small_calls_run_on_one_thread(monkeypatch):
    # Below _PARALLEL_ENTRIES n x n terms a call is not worth a parallel region (the RBF policy's n = 50).
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    assert se_moments._threads(se_moments._PARALLEL_ENTRIES - 1) == 1
    assert se_moments._threads(se_moments._PARALLEL_ENTRIES) == 2
