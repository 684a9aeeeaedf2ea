"""The native SE-kernel moments (`se_moments.c`) against the fused torch formulation: values, gradients, rollouts."""

from __future__ import annotations

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from qtl.gaussian import Gaussian, element_failures
from qtl.kernels import SEKernelMoments
from qtl.kernels.engine import Engine
from qtl.kernels.native import build as native_build
from qtl.kernels.native import se_moments, se_moments_check
from qtl.kernels.native.se_moments import NativeSEKernelMoments, load_se_moments
from qtl.kernels.native.se_moments_check import check_against_torch
from qtl.propagation import MomentMatching
from tests.helpers import quadratic_reward
from tests.propagation.restarts import random_start, spread_restarts
from tests.propagation.test_moment_matching_formulations import make_policy
from tests.test_features import assert_rel_close

DTYPE = torch.float64
RTOL = 1e-12
ROLLOUT_RTOL = 1e-11
NAMES = ("mean", "cov", "inputs", "beta", "lengthscales", "signal_variance")


@pytest.fixture(scope="module")
def library(built):
    """The compiled library (built once for the module)."""
    return load_se_moments()


def make_problem(
    num_out: int, dim: int, num: int, state_batch: tuple[int, ...], const_batch: tuple[int, ...], seed: int
) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Leaves of a random problem (Gaussian input with `state_batch`, regressors with `const_batch`) and a K⁻¹."""
    gen = torch.Generator().manual_seed(seed)
    root = torch.randn(*state_batch, dim, dim, generator=gen, dtype=DTYPE) / dim**0.5
    leaves = {
        "mean": 0.5 * torch.randn(*state_batch, dim, generator=gen, dtype=DTYPE),
        "cov": root @ root.mT + 0.05 * torch.eye(dim, dtype=DTYPE),
        "inputs": torch.randn(*const_batch, num, dim, generator=gen, dtype=DTYPE),
        "beta": torch.randn(*const_batch, num_out, num, generator=gen, dtype=DTYPE),
        "lengthscales": 0.6 + torch.rand(*const_batch, num_out, dim, generator=gen, dtype=DTYPE),
        "signal_variance": 0.5 + torch.rand(*const_batch, num_out, generator=gen, dtype=DTYPE),
    }
    k_root = torch.randn(*const_batch, num_out, num, num, generator=gen, dtype=DTYPE)
    return {k: v.requires_grad_() for k, v in leaves.items()}, 0.1 * k_root @ k_root.mT / num


FUSED, NATIVE = Engine(moments="fused"), Engine(moments="native")
# The native moments with every pair's full n x n exp sum (the form before the lower sums).
FULL_PAIRS = Engine(moments="native", lower_pairs=False)


def outputs_and_grads(
    leaves: dict[str, torch.Tensor], k_inv: torch.Tensor | None, engine: Engine, probes: list[torch.Tensor] | None
) -> tuple[list[torch.Tensor], list[torch.Tensor | None]]:
    """(mean, cov, gain) of `_fused_call` by ``engine``, and the gradients of Σ probe·output."""
    moments = SEKernelMoments(
        leaves["inputs"], leaves["beta"], leaves["lengthscales"], leaves["signal_variance"], k_inv
    )
    outs = list(moments._fused_call(leaves["mean"], leaves["cov"], engine))
    if probes is None:  # plain sums and a transposed view: expanded and strided output gradients
        loss = outs[0].sum() + (outs[1].mT * outs[1].detach()).sum() + outs[2].mT[..., 0, :].sum()
    else:
        loss = sum((o * p).sum() for o, p in zip(outs, probes, strict=True))
    wanted = [t for t in leaves.values() if t.requires_grad]
    return outs, list(torch.autograd.grad(loss, wanted, allow_unused=True))


def assert_native_equals_fused(leaves, k_inv, seed: int = 0, probes: bool = True) -> None:
    """Values and gradients of every leaf that needs one: native equal to fused to RTOL (relative to the max)."""
    shapes = [
        o.shape
        for o in SEKernelMoments(
            leaves["inputs"], leaves["beta"], leaves["lengthscales"], leaves["signal_variance"], k_inv
        )._fused_call(leaves["mean"], leaves["cov"], FUSED)
    ]
    gen = torch.Generator().manual_seed(seed)
    weights = [torch.randn(s, generator=gen, dtype=DTYPE) for s in shapes] if probes else None
    want_out, want_grads = outputs_and_grads(leaves, k_inv, FUSED, weights)
    got_out, got_grads = outputs_and_grads(leaves, k_inv, NATIVE, weights)
    for what, got, want in zip(("mean", "cov", "gain"), got_out, want_out, strict=True):
        assert_rel_close(got, want, what, rtol=RTOL)
    names = [k for k, v in leaves.items() if v.requires_grad]
    assert names, "no gradient to compare"
    for what, got, want in zip(names, got_grads, want_grads, strict=True):
        assert want is not None and got is not None, what
        assert want.abs().max() > 0, f"{what}: a zero gradient compares nothing"
        assert_rel_close(got, want, f"∂/∂{what}", rtol=RTOL)


# (E, D, n, state batch, constants' batch): odd sizes, size 1, broadcasting either way and both.
SHAPES = [
    (3, 5, 7, (), ()),
    (1, 1, 1, (), ()),
    (2, 3, 1, (2,), ()),
    (4, 6, 33, (3,), ()),
    (3, 2, 11, (), (2,)),
    (2, 4, 9, (2, 1), (3,)),
    (3, 3, 5, (4,), (4,)),
    (1, 5, 300, (2,), (1,)),
]


@pytest.mark.parametrize("with_k_inv", [True, False], ids=["gp0", "gp2"])
@pytest.mark.parametrize(("num_out", "dim", "num", "state_batch", "const_batch"), SHAPES)
def test_native_equals_fused_all_gradients(library, num_out, dim, num, state_batch, const_batch, with_k_inv):
    """Every leaf needs a gradient (the weights too: backward recomputes the n x n sums)."""
    leaves, k_inv = make_problem(num_out, dim, num, state_batch, const_batch, seed=num + dim)
    assert_native_equals_fused(leaves, k_inv if with_k_inv else None, seed=num_out)


@pytest.mark.parametrize(("num_out", "dim", "num", "state_batch", "const_batch"), SHAPES)
def test_native_equals_fused_dynamics_gradients(library, num_out, dim, num, state_batch, const_batch):
    """As in policy search: β (so the weights) needs no gradient, so the forward keeps G_A and G_B."""
    leaves, k_inv = make_problem(num_out, dim, num, state_batch, const_batch, seed=2 * num + dim)
    leaves["beta"].requires_grad_(False)
    assert_native_equals_fused(leaves, k_inv, seed=1)
    for name in ("inputs", "lengthscales", "signal_variance"):
        leaves[name].requires_grad_(False)
    assert_native_equals_fused(leaves, k_inv, seed=2)  # mean and cov only, as in a rollout


@pytest.mark.parametrize("with_k_inv", [True, False], ids=["gp0", "gp2"])
def test_strided_and_expanded_output_gradients(library, with_k_inv):
    leaves, k_inv = make_problem(3, 4, 13, (2, 3), (3,), seed=7)
    assert_native_equals_fused(leaves, k_inv if with_k_inv else None, probes=False)


def test_expanded_and_transposed_operands(library):
    """Broadcast views (stride 0) and non-contiguous operands, as a batched policy hands them over."""
    leaves, _ = make_problem(2, 3, 8, (), (), seed=3)
    mean, cov = leaves["mean"].expand(4, 3), leaves["cov"].mT.expand(4, 3, 3)
    moments = SEKernelMoments(leaves["inputs"], leaves["beta"], leaves["lengthscales"], leaves["signal_variance"])
    results = []
    for engine in (FUSED, NATIVE):
        outs = moments._fused_call(mean, cov, engine)
        loss = sum((o * (i + 1.5)).square().sum() for i, o in enumerate(outs))
        results.append((*outs, *torch.autograd.grad(loss, list(leaves.values()), retain_graph=True)))
    for what, got, want in zip(("mean", "cov", "gain", *NAMES), results[1], results[0], strict=True):
        assert_rel_close(got, want, what, rtol=RTOL)


def test_native_path_is_taken_only_for_float64_cpu(library, monkeypatch):
    calls = []
    original = se_moments.NativeSEKernelMoments.apply

    def spy(*args):
        calls.append(args[0].dtype)
        return original(*args)

    monkeypatch.setattr(se_moments.NativeSEKernelMoments, "apply", spy)
    leaves, _ = make_problem(2, 3, 6, (2,), (), seed=5)
    single = {k: v.detach().float() for k, v in leaves.items()}
    state32 = Gaussian(single["mean"], single["cov"])
    results32 = []
    for engine in (NATIVE, FUSED):
        moments64 = SEKernelMoments(leaves["inputs"], leaves["beta"], leaves["lengthscales"], leaves["signal_variance"],
                                    engine=engine)
        moments32 = SEKernelMoments(single["inputs"], single["beta"], single["lengthscales"], single["signal_variance"],
                                    engine=engine)
        results32.append(moments32(state32))
        assert calls == ([] if engine is NATIVE else [DTYPE])  # float32 takes the fused torch code
        moments64(Gaussian(leaves["mean"], leaves["cov"]))
        assert calls == [DTYPE]
    got32, want32 = results32
    assert calls == [DTYPE]  # fused never takes it
    for got, want in zip((got32.mean, got32.cov, got32.gain), (want32.mean, want32.cov, want32.gain), strict=True):
        assert got.dtype == torch.float32 and torch.equal(got, want)


def test_gradcheck_all_operands(library):
    """torch.autograd.gradcheck of the Function itself, every operand (weights included) differentiable."""
    leaves, k_inv = make_problem(2, 3, 4, (2,), (), seed=11)
    moments = SEKernelMoments(
        leaves["inputs"], leaves["beta"], leaves["lengthscales"], leaves["signal_variance"], k_inv
    )
    operands = [
        t.detach().clone().requires_grad_()
        for t in (leaves["mean"], leaves["cov"], *(getattr(moments, a) for a in ("inputs", "beta", "inv_ls")))
    ]
    operands += [moments.log_sf2.detach().clone().requires_grad_(), moments.weights.detach().clone().requires_grad_()]

    def fn(mean, cov, *ops):  # Σ symmetric, as the formula (and its symmetrized gradient) assumes
        return NativeSEKernelMoments.apply(mean, 0.5 * (cov + cov.mT), *ops, library, torch.is_grad_enabled(), True)

    assert torch.autograd.gradcheck(fn, tuple(operands), eps=1e-6, atol=1e-8, rtol=1e-6)


def test_gradcheck_with_constant_weights(library):
    """The path that keeps G_A, G_B from the forward pass (weights without gradient), broadcast constants."""
    leaves, k_inv = make_problem(3, 2, 5, (2,), (), seed=12)
    moments = SEKernelMoments(
        leaves["inputs"], leaves["beta"], leaves["lengthscales"], leaves["signal_variance"], k_inv
    )
    mean, cov = (t.detach().clone().requires_grad_() for t in (leaves["mean"], leaves["cov"]))
    inputs, inv_ls, log_sf2 = (
        t.detach().clone().requires_grad_() for t in (moments.inputs, moments.inv_ls, moments.log_sf2)
    )
    beta, weights = moments.beta.detach(), moments.weights.detach()

    def fn(mean, cov, inputs, inv_ls, log_sf2):
        cov = 0.5 * (cov + cov.mT)
        return NativeSEKernelMoments.apply(mean, cov, inputs, beta, inv_ls, log_sf2, weights, library, True, True)

    assert torch.autograd.gradcheck(fn, (mean, cov, inputs, inv_ls, log_sf2), eps=1e-6, atol=1e-8, rtol=1e-6)


def test_not_positive_definite_raises_like_cholesky(library):
    leaves, _ = make_problem(2, 3, 4, (), (), seed=13)
    moments = SEKernelMoments(leaves["inputs"], leaves["beta"], leaves["lengthscales"], leaves["signal_variance"])
    cov = -torch.eye(3, dtype=DTYPE)
    for engine in (FUSED, NATIVE):
        with pytest.raises(torch.linalg.LinAlgError):
            moments._fused_call(leaves["mean"].detach(), cov, engine)


@pytest.mark.parametrize("with_k_inv", [True, False], ids=["gp0", "gp2"])
@pytest.mark.parametrize("beta_grad", [False, True], ids=["forward-keeps", "recomputes"])
def test_a_failing_item_is_nan_and_the_others_as_without_it(library, with_k_inv, beta_grad):
    """Inside element_failures, item 1 of 3 not positive-definite: NaN outputs and gradients there, natively as in
    torch (a broadcast operand's gradient sums it: NaN); the other items' outputs and gradients native equal to
    fused, and bit for bit those of the batch where item 1 does not fail."""
    results = {}
    for flip in (-1.0, 1.0):
        leaves, k_inv = make_problem(3, 4, 9, (3,), (), seed=5)
        leaves["beta"].requires_grad_(beta_grad)
        cov = leaves["cov"].detach().clone()
        cov[1] *= flip
        leaves["cov"] = cov.requires_grad_()
        for engine in (FUSED, NATIVE):
            with element_failures() as masks:
                outs, grads = outputs_and_grads(leaves, k_inv if with_k_inv else None, engine, None)
            assert bool(masks) == (flip < 0)
            results[flip, engine.moments] = outs, dict(zip([k for k, v in leaves.items() if v.requires_grad], grads,
                                                           strict=True))
    good = [0, 2]
    (native_outs, native_grads), (fused_outs, fused_grads) = results[-1.0, "native"], results[-1.0, "fused"]
    clean_outs, clean_grads = results[1.0, "native"]
    for what, got, want, clean in zip(("mean", "cov", "gain"), native_outs, fused_outs, clean_outs, strict=True):
        assert got[1].isnan().all() and want[1].isnan().all(), what
        assert_rel_close(got[good], want[good], what, rtol=RTOL)
        assert torch.equal(got[good], clean[good]), what
    for name, got in native_grads.items():
        want = fused_grads[name]
        if name in ("mean", "cov"):  # per item
            assert got[1].isnan().all() and want[1].isnan().all(), name
            assert_rel_close(got[good], want[good], f"∂/∂{name}", rtol=RTOL)
            assert torch.equal(got[good], clean_grads[name][good]), name
        else:  # broadcast over the items: the failed one's NaN is in the sum
            assert got.isnan().all() and want.isnan().all(), name


class _OpCounter(TorchDispatchMode):
    """Counts the aten operations dispatched inside the ``with`` block."""

    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.count += 1
        return func(*args, **(kwargs or {}))


def count_ops(moments: SEKernelMoments, mean: torch.Tensor, cov: torch.Tensor, engine: Engine) -> tuple[int, int]:
    """Dispatched operations of one ``_fused_call`` by ``engine``: forward, and backward from given output gradients."""
    with _OpCounter() as forward:
        outs = moments._fused_call(mean, cov, engine)
    grads = [torch.ones_like(o) for o in outs]
    leaves = [t for t in (mean, cov) if t.requires_grad]
    with _OpCounter() as backward:
        torch.autograd.grad(outs, leaves, grads)
    return forward.count, backward.count


@pytest.mark.parametrize("with_k_inv", [True, False], ids=["dynamics", "policy"])
def test_one_call_dispatches_a_handful_of_ops(library, with_k_inv):
    leaves, k_inv = make_problem(4, 6, 25, (3,), (), seed=17)
    # The GP in policy search: constants without gradient; the RBF policy: all but α² (a constant) need one,
    # so backward allocates one gradient per operand (6) and makes one compiled call.
    constants = ("inputs", "beta", "lengthscales", "signal_variance") if with_k_inv else ("signal_variance",)
    for name in constants:
        leaves[name].requires_grad_(False)
    moments = SEKernelMoments(
        leaves["inputs"],
        leaves["beta"],
        leaves["lengthscales"],
        leaves["signal_variance"],
        k_inv if with_k_inv else None,
    )
    fused_counts = count_ops(moments, leaves["mean"], leaves["cov"], FUSED)
    native_counts = count_ops(moments, leaves["mean"], leaves["cov"], NATIVE)
    assert native_counts[0] <= 6 and native_counts[1] <= 6, native_counts
    assert fused_counts[0] > 5 * native_counts[0] and fused_counts[1] > 5 * native_counts[1], fused_counts


def test_check_against_torch_passes_and_can_fail(library, monkeypatch):
    check_against_torch(library)
    monkeypatch.setattr(se_moments_check, "CHECK_RTOL", -1.0)
    with pytest.raises(RuntimeError, match="disagree with torch"):
        check_against_torch(library)
    with pytest.raises(native_build.BuildError, match="disagree with torch"):
        check_against_torch(library, error=native_build.BuildError)


@pytest.mark.parametrize(("restarts", "models"), [(1, 1), (3, 1), (1, 2)])
def test_rollout_native_equals_fused(library, gp_factory, restarts, models):
    """V and ∂V/∂ψ of a whole MomentMatching rollout (restarts `R`, stacked models `M`) agree to 1e-11."""
    gps = [gp_factory(30, 3, 1, (1,), seed=71 + m) for m in range(models)]
    model = [g.posterior_cache() for g in gps] if models > 1 else gps[0]
    policy = make_policy("rbf", 4)
    if restarts > 1:
        policy = spread_restarts(policy, restarts)
    def propagator(engine: Engine) -> MomentMatching:
        return MomentMatching(model, policy, quadratic_reward(3, (1,)), angle_dims=(1,), include_noise=True,
                              engine=engine)

    gen = torch.Generator().manual_seed(10 * restarts + models)
    start = random_start(models, gen)
    psi = list(policy.parameters())
    calls = []
    original = se_moments.NativeSEKernelMoments.apply

    def spy(*args):
        calls.append(1)
        return original(*args)

    fused = propagator(FUSED).expected_return(start, 5)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(se_moments.NativeSEKernelMoments, "apply", spy)
        native = propagator(NATIVE).expected_return(start, 5)
    assert len(calls) == 2 * 5  # policy and dynamics, every step
    assert native.shape == fused.shape == ((restarts,) if restarts > 1 else (models,) if models > 1 else ())
    assert_rel_close(native, fused, "V", rtol=ROLLOUT_RTOL)
    weights = torch.randn(fused.shape, generator=gen, dtype=DTYPE)
    grads_fused = torch.autograd.grad((fused * weights).sum(), psi)
    grads_native = torch.autograd.grad((native * weights).sum(), psi)
    for p, g, w in zip(psi, grads_native, grads_fused, strict=True):
        assert g.shape == p.shape and w.abs().max() > 0
        assert_rel_close(g, w, "∂V/∂ψ", rtol=ROLLOUT_RTOL)


def native_outputs_and_grads(leaves, k_inv, probes, engine: Engine = NATIVE) -> list[torch.Tensor]:
    """(mean, cov, gain) of the native moments and the gradients of Σ probe·output for every leaf that needs one."""
    outs, grads = outputs_and_grads(leaves, k_inv, engine, probes)
    return [*outs, *grads]


@pytest.mark.parametrize(("num_out", "dim", "num", "state_batch", "const_batch"), SHAPES)
@pytest.mark.parametrize("weights_grad", [True, False], ids=["recompute", "fused"])
def test_lower_pair_sums_equal_the_full_sums(library, num_out, dim, num, state_batch, const_batch, weights_grad):
    """The a = b pairs' exp sums from their lower triangles (the default) against every pair's full sum."""
    leaves, k_inv = make_problem(num_out, dim, num, state_batch, const_batch, seed=3 * num + dim)
    leaves["beta"].requires_grad_(weights_grad)  # β enters the weights: with it, backward recomputes the sums
    gen = torch.Generator().manual_seed(num)
    shapes = [o.shape for o in outputs_and_grads(leaves, k_inv, NATIVE, None)[0]]
    probes = [torch.randn(s, generator=gen, dtype=DTYPE) for s in shapes]
    lower = native_outputs_and_grads(leaves, k_inv, probes)
    full = native_outputs_and_grads(leaves, k_inv, probes, FULL_PAIRS)
    assert len(lower) == len(full) == 3 + 5 + weights_grad
    for i, (got, want) in enumerate(zip(lower, full, strict=True)):
        assert_rel_close(got, want, f"output or gradient {i}", rtol=RTOL)


def test_rollout_lower_pair_sums_equal_the_full_sums(library, gp_factory):
    """V and ∂V/∂ψ of a rollout on a 4-output GP with n = 300 (the sparse GP's size), restarts in lockstep."""
    gp = gp_factory(300, 4, 1, (1,), seed=5)
    policy = spread_restarts(make_policy("rbf", 5), 2)  # features: 4 states, the angle as sin and cos
    gen = torch.Generator().manual_seed(6)
    root = 0.3 * torch.randn(4, 4, generator=gen, dtype=DTYPE)
    start = Gaussian(0.3 * torch.randn(4, generator=gen, dtype=DTYPE), root @ root.T + 0.01 * torch.eye(4, dtype=DTYPE))
    psi = list(policy.parameters())
    lower, full = (MomentMatching(gp, policy, quadratic_reward(4, (1,)), angle_dims=(1,), engine=engine)
                   .expected_return(start, 4) for engine in (NATIVE, FULL_PAIRS))
    assert_rel_close(lower, full, "V", rtol=ROLLOUT_RTOL)
    for p, got, want in zip(psi, torch.autograd.grad(lower.sum(), psi), torch.autograd.grad(full.sum(), psi),
                            strict=True):
        assert got.shape == p.shape and want.abs().max() > 0
        assert_rel_close(got, want, "∂V/∂ψ", rtol=ROLLOUT_RTOL)
