"""The native angle features and sine squashing (`trig.c`) against the fused torch code, and the switch to them."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import Tensor

from qtl.features import AngleFeatures
from qtl.gaussian import Gaussian, MomentMatch, symmetrize
from qtl.kernels.engine import Engine
from qtl.kernels.native import trig as native_trig
from qtl.policies import LinearPolicy, SquashedPolicy, sin_squash_moments
from qtl.policies.squash import _squash_terms, _SquashWeights
from qtl.propagation import MomentMatching
from tests.helpers import quadratic_reward
from tests.propagation.restarts import random_start, spread_restarts
from tests.propagation.test_moment_matching_formulations import make_policy
from tests.test_features import assert_rel_close

DTYPE = torch.float64
RTOL = 1e-12  # native vs fused, relative to each tensor's largest entry
ROLLOUT_RTOL = 1e-11

# (D, angle dims, batch of the mean, batch of the covariance): size 1, one angle first or last,
# several angles out of order, every dim an angle, batches broadcast both ways.
FEATURE_SHAPES = [
    (1, (0,), (), ()),
    (4, (1,), (3,), ()),
    (5, (3, 0), (2, 1), (3,)),
    (6, (0, 2, 5), (), (2,)),
    (3, (2, 0, 1), (1,), (4,)),
    (7, (6,), (2, 3), (2, 1)),
]
# (F, batch of the mean, batch of the covariance, the bound).
SQUASH_SHAPES = [
    (1, (), (), (2.0,)),
    (1, (4,), (), (0.7,)),
    (2, (), (3,), (1.0, 3.0)),
    (3, (2, 1), (3,), (1.5, 0.5, 2.0)),
    (5, (2, 3), (2, 3), (1.0, 2.0, 0.3, 4.0, 1.1)),
]


@pytest.fixture
def native(built: Path) -> Engine:
    """The native formulation (the library built)."""
    return Engine(moments="native")


def gaussian(dim: int, batch_mean: tuple, batch_cov: tuple, seed: int, scale: float = 0.7) -> tuple[Tensor, Tensor]:
    """A random mean and SPD covariance (leaves requiring grad) of the given batch shapes."""
    gen = torch.Generator().manual_seed(seed)
    mean = torch.randn(*batch_mean, dim, generator=gen, dtype=DTYPE)
    root = scale * torch.randn(*batch_cov, dim, dim, generator=gen, dtype=DTYPE) / dim**0.5
    cov = root @ root.mT + 1e-3 * torch.eye(dim, dtype=DTYPE)
    return mean.requires_grad_(), cov.requires_grad_()


def assert_same_with_grads(native: tuple[Tensor, ...], fused: tuple[Tensor, ...], inputs: tuple[Tensor, ...]) -> None:
    """Values, and the gradients w.r.t. ``inputs`` of a random weighting of all outputs and of their plain sum
    (upstream gradients that are expanded, not contiguous), agree to RTOL."""
    gen = torch.Generator().manual_seed(7)
    weights = [torch.randn(t.shape, generator=gen, dtype=DTYPE) for t in fused]
    for i, (got, want) in enumerate(zip(native, fused, strict=True)):
        assert_rel_close(got, want, f"output {i}", RTOL)
    for weighted in (False, True):
        grads = [
            torch.autograd.grad(
                sum((w * t).sum() if weighted else t.sum() for w, t in zip(weights, outs, strict=True)),
                inputs,
                retain_graph=not weighted,
            )
            for outs in (native, fused)
        ]
        for i, (got, want) in enumerate(zip(*grads, strict=True)):
            assert torch.isfinite(want).all()
            assert_rel_close(got, want, f"gradient {i} ({'weighted' if weighted else 'sum'})", RTOL)


def feature_moments(features: AngleFeatures, mean: Tensor, cov: Tensor, name: str) -> tuple[Tensor, ...]:
    """:meth:`AngleFeatures.moments` under formulation ``name``, as a tuple."""
    out = features.moments(Gaussian(mean, cov), Engine(moments=name))
    return out.mean, out.cov, out.cross_cov, out.gain


@pytest.mark.parametrize(("dim", "angles", "batch_mean", "batch_cov"), FEATURE_SHAPES)
def test_angle_features_equal_the_fused_code(built, dim, angles, batch_mean, batch_cov):
    mean, cov = gaussian(dim, batch_mean, batch_cov, seed=dim)
    features = AngleFeatures(dim, angles)
    native = feature_moments(features, mean, cov, "native")
    fused = feature_moments(features, mean, cov, "fused")
    batch = torch.broadcast_shapes(batch_mean, batch_cov)
    assert native[0].shape == (*batch, dim + len(angles)) and native[2].shape == (*batch, dim, dim + len(angles))
    assert torch.equal(native[1], native[1].mT)
    assert native[0].grad_fn is not None and "NativeAngleFeatures" in native[0].grad_fn.name()
    assert_same_with_grads(native, fused, (mean, cov))


def test_angle_features_cov_gradient_keeps_the_fused_convention(built):
    """The gradient w.r.t. a non-symmetric covariance is the fused code's, entry by entry (not symmetrized)."""
    mean, cov = gaussian(5, (2,), (2,), seed=3)
    skew = 0.05 * torch.randn(2, 5, 5, generator=torch.Generator().manual_seed(1), dtype=DTYPE)
    cov_asym = (cov.detach() + skew).requires_grad_()
    features = AngleFeatures(5, (4, 1, 2))
    native = feature_moments(features, mean, cov_asym, "native")
    fused = feature_moments(features, mean, cov_asym, "fused")
    assert_same_with_grads(native, fused, (mean, cov_asym))
    native = feature_moments(features, mean, cov_asym, "native")
    grad = torch.autograd.grad(native[1][..., -1, :].sum() + native[2].sum(), cov_asym)[0]
    assert not torch.allclose(grad, grad.mT)  # the comparison above did see an asymmetric gradient


def test_angle_features_without_angles_are_the_identity(native):
    mean, cov = gaussian(3, (2,), (2,), seed=0)
    out = AngleFeatures(3).moments(Gaussian(mean, cov), native)
    assert out.mean is mean and out.cov is cov and torch.equal(out.gain, torch.eye(3, dtype=DTYPE).expand(2, 3, 3))


def squash_terms(mean: Tensor, cov: Tensor, bound: Tensor, name: str) -> tuple[Tensor, ...]:
    """(mean, symmetrized cov, slope `... x 1 x F`) of the squashing under formulation ``name``."""
    if name == "native":
        return native_trig.sin_squash_terms(mean, cov, bound)
    out_mean, out_cov, slope = _squash_terms(mean, cov, _SquashWeights.of(bound))
    return out_mean, symmetrize(out_cov), slope[..., None, :]


@pytest.mark.parametrize(("num", "batch_mean", "batch_cov", "bound"), SQUASH_SHAPES)
def test_sin_squash_terms_equal_the_fused_code(built, num, batch_mean, batch_cov, bound):
    mean, cov = gaussian(num, batch_mean, batch_cov, seed=10 + num)
    bound = torch.tensor(bound, dtype=DTYPE)
    native = squash_terms(mean, cov, bound, "native")
    assert native[0].shape == (*torch.broadcast_shapes(batch_mean, batch_cov), num)
    assert_same_with_grads(native, squash_terms(mean, cov, bound, "fused"), (mean, cov))


@pytest.mark.parametrize("skew", [0.0, 0.05])
def test_sin_squash_moments_and_the_squashed_policy_equal_the_fused_code(built, skew):
    """sin_squash_moments, and SquashedPolicy.prepare (with a restart batch `R` in ψ), under native and fused."""
    mean, cov = gaussian(2, (3,), (), seed=5)
    cov_in = (cov.detach() + skew * torch.tensor([[0.0, 1.0], [-1.0, 0.0]], dtype=DTYPE)).requires_grad_()
    bound = torch.tensor([1.0, 2.5], dtype=DTYPE)

    def moments(name: str) -> tuple[Tensor, ...]:
        out = sin_squash_moments(Gaussian(mean, cov_in), bound, Engine(moments=name))
        return out.mean, out.cov, out.cross_cov, out.gain

    assert_same_with_grads(moments("native"), moments("fused"), (mean, cov_in))

    policy = spread_restarts(SquashedPolicy(LinearPolicy(3, 2, generator=torch.Generator().manual_seed(2)), 1.5))
    x_mean, x_cov = gaussian(3, (), (), seed=6)

    def prepared(name: str) -> tuple[Tensor, ...]:
        out: MomentMatch = policy.prepare(Engine(moments=name))(Gaussian(x_mean, x_cov))
        return out.mean, out.cov, out.cross_cov, out.gain

    native = prepared("native")
    assert native[0].shape == (3, 2) and "NativeSinSquash" in native[1].grad_fn.name()
    assert_same_with_grads(native, prepared("fused"), (x_mean, x_cov, *policy.parameters()))


def test_gradcheck_native_functions(built):
    library = native_trig.load_trig()
    mean, cov = gaussian(4, (2,), (2,), seed=1)
    inputs = (mean.detach().requires_grad_(), cov.detach().requires_grad_())
    assert torch.autograd.gradcheck(
        lambda m, c: native_trig.NativeAngleFeatures.apply(m, c, (2, 0), library), inputs, eps=1e-6, atol=1e-8
    )
    mean, cov = gaussian(2, (3,), (3,), seed=2)
    inputs = (mean.detach().requires_grad_(), cov.detach().requires_grad_())
    bound = torch.tensor([1.0, 2.0], dtype=DTYPE)
    assert torch.autograd.gradcheck(
        lambda m, c: native_trig.NativeSinSquash.apply(m, c, bound, library), inputs, eps=1e-6, atol=1e-8
    )


def test_other_dtypes_take_the_torch_path(native, monkeypatch):
    """float32 operands under kernels.moments=native run the fused torch code, bit for bit."""

    def refuse(*args: object) -> None:
        raise AssertionError("the native Function ran on float32 operands")

    monkeypatch.setattr(native_trig.NativeAngleFeatures, "apply", refuse)
    monkeypatch.setattr(native_trig.NativeSinSquash, "apply", refuse)
    mean, cov = (t.detach().float() for t in gaussian(3, (2,), (), seed=4))
    features = AngleFeatures(3, (1,))
    got = features.moments(Gaussian(mean, cov), native)
    bound = torch.tensor([1.0, 2.0, 3.0])
    squashed = sin_squash_moments(Gaussian(mean, cov), bound, native)
    fused = Engine(moments="fused")
    want = features.moments(Gaussian(mean, cov), fused)
    want_squashed = sin_squash_moments(Gaussian(mean, cov), bound, fused)
    assert got.mean.dtype == torch.float32
    for g, w in zip(
        (got.mean, got.cov, got.gain, squashed.mean, squashed.cov),
        (want.mean, want.cov, want.gain, want_squashed.mean, want_squashed.cov),
        strict=True,
    ):
        assert torch.equal(g, w)
    with pytest.raises(AssertionError, match="float32"):  # the float64 path does take it
        features.moments(Gaussian(mean.double(), cov.double()), native)


def test_large_variance_is_finite_and_zero_covariance_gives_zero(built):
    """σ² ≈ 1e3 (e^{σ²} would overflow) stays finite with finite gradients; Σ = 0 gives an exactly zero output cov."""
    features = AngleFeatures(3, (0, 2))
    bound = torch.tensor([1.0, 2.0, 3.0], dtype=DTYPE)
    for scale in (1e3, 5e4):
        mean = torch.tensor([0.3, -1.0, 2.0], dtype=DTYPE, requires_grad=True)
        cov = (scale * torch.tensor([[1.0, 0.2, 0.5], [0.2, 1.0, 0.1], [0.5, 0.1, 1.2]], dtype=DTYPE)).requires_grad_()
        native = feature_moments(features, mean, cov, "native") + squash_terms(mean, cov, bound, "native")
        assert all(torch.isfinite(t).all() for t in native)
        grads = torch.autograd.grad(sum(t.sum() for t in native), (mean, cov))
        assert all(torch.isfinite(g).all() for g in grads)
        fused = feature_moments(features, mean, cov, "fused") + squash_terms(mean, cov, bound, "fused")
        for got, want in zip(native, fused, strict=True):
            assert_rel_close(got, want, "large variance", 1e-10)
    # Far spread angles: sin and cos are uncorrelated with variance ½.
    trig = native[1][..., 1:, 1:]
    torch.testing.assert_close(trig, 0.5 * torch.eye(4, dtype=DTYPE), atol=1e-12, rtol=0)

    mean = torch.tensor([0.3, -1.0, 2.0], dtype=DTYPE, requires_grad=True)
    zero = torch.zeros(3, 3, dtype=DTYPE, requires_grad=True)
    out_mean, out_cov, cross_cov, _ = feature_moments(features, mean, zero, "native")
    assert torch.equal(out_cov, torch.zeros_like(out_cov)) and torch.equal(cross_cov, torch.zeros_like(cross_cov))
    torch.testing.assert_close(out_mean, AngleFeatures(3, (0, 2))(mean.detach()), atol=0, rtol=0)
    squash_mean, squash_cov, _ = squash_terms(mean, zero, bound, "native")
    assert torch.equal(squash_cov, torch.zeros_like(squash_cov))
    torch.testing.assert_close(squash_mean, bound * (9 * mean.sin() + (3 * mean).sin()) / 8, atol=1e-14, rtol=0)


@pytest.mark.parametrize(
    ("kind", "restarts", "models"), [("rbf", 1, 1), ("rbf", 3, 1), ("rbf", 1, 2), ("linear", 3, 1), ("linear", 1, 3)]
)
def test_native_rollout_equals_fused(built, gp_factory, monkeypatch, kind, restarts, models):
    """V and ∂V/∂ψ of a MomentMatching rollout (restarts `R`, stacked models `M`): native equals fused to 1e-11."""
    calls = {"features": 0, "squash": 0}
    for name, fn in (("features", native_trig.NativeAngleFeatures), ("squash", native_trig.NativeSinSquash)):

        def counted(*args: object, _name: str = name, _apply=fn.apply) -> object:
            calls[_name] += 1
            return _apply(*args)

        monkeypatch.setattr(fn, "apply", counted)
    gps = [gp_factory(30, 3, 1, (1,), seed=51 + m) for m in range(models)]
    model = [g.posterior_cache() for g in gps] if models > 1 else gps[0]
    policy = make_policy(kind, 4)
    if restarts > 1:
        policy = spread_restarts(policy, restarts)
    def propagator(moments: str) -> MomentMatching:
        return MomentMatching(model, policy, quadratic_reward(3, (1,)), angle_dims=(1,), engine=Engine(moments=moments))

    gen = torch.Generator().manual_seed(restarts + models)
    start = random_start(models, gen)
    psi = list(policy.parameters())
    fused = propagator("fused").expected_return(start, 6)
    assert calls == {"features": 0, "squash": 0}
    native = propagator("native").expected_return(start, 6)
    assert calls["features"] >= 6 and calls["squash"] >= 6
    assert native.shape == fused.shape
    assert_rel_close(native, fused, "V", ROLLOUT_RTOL)
    weights = torch.randn(fused.shape, generator=gen, dtype=DTYPE)
    for p, got, want in zip(
        psi,
        torch.autograd.grad((native * weights).sum(), psi),
        torch.autograd.grad((fused * weights).sum(), psi),
        strict=True,
    ):
        assert got.shape == p.shape
        assert_rel_close(got, want, "∂V/∂ψ", ROLLOUT_RTOL)
