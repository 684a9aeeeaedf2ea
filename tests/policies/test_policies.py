"""Policies: RBF network (Eq. 5), linear, sine squashing — values, exact moments, gradients, ψ."""

from __future__ import annotations

import itertools

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from qtl.gaussian import Gaussian
from qtl.kernels.engine import FORMULATIONS, Engine
from qtl.policies import (
    POLICY_NOISE_VARIANCE,
    LinearPolicy,
    RBFPolicy,
    SquashedPolicy,
    batched_policy,
    sin_squash,
    sin_squash_moments,
)
from tests.propagation.restarts import spread_restarts
from tests.test_features import assert_formulations_agree, random_state

DTYPE = torch.float64
NUM_SAMPLES = 100_000


@pytest.fixture(params=FORMULATIONS)
def engine(request) -> Engine:
    """Each formulation of the moments in turn (torch exp sums)."""
    return Engine(moments=request.param)


def make_rbf(input_dim: int = 3, output_dim: int = 2, num_basis: int = 6, seed: int = 0) -> RBFPolicy:
    gen = torch.Generator().manual_seed(seed)
    return RBFPolicy(
        input_dim,
        output_dim,
        num_basis,
        targets=torch.randn(num_basis, output_dim, generator=gen, dtype=DTYPE),
        lengthscales=0.7 + torch.rand(output_dim, input_dim, generator=gen, dtype=DTYPE),
        generator=gen,
    )


def make_policy(kind: str, seed: int = 0):
    if kind == "rbf":
        return make_rbf(seed=seed)
    if kind == "linear":
        return LinearPolicy(3, 2, generator=torch.Generator().manual_seed(seed))
    if kind == "squashed-rbf":
        return SquashedPolicy(make_rbf(seed=seed), [2.0, 0.5])
    return SquashedPolicy(LinearPolicy(3, 2, generator=torch.Generator().manual_seed(seed)), 3.0)


KINDS = ["rbf", "linear", "squashed-rbf", "squashed-linear"]
# Kinds whose moments are exact for a Gaussian input. Squashing a linear policy is exact (z is
# Gaussian); squashing an RBF network squashes the moment-matched Gaussian of z, which is not
# the distribution of z (PILCO's approximation), so that kind is checked loosely below.
EXACT_KINDS = ["rbf", "linear", "squashed-linear"]
# Loose check of squashed RBF moments: errors relative to the MC output spread.
APPROX_MEAN_TOL = 0.15  # |Δ mean| in output standard deviations
APPROX_COV_TOL = 0.25  # relative Frobenius error of covariance and input–output covariance


def test_rbf_interpolates_its_targets():
    # β_π = (K_π + σ_π²I)⁻¹ y_π: at well separated support points π(X_π) ≈ y_π, shrunk by σ_π².
    support = torch.tensor([[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]], dtype=DTYPE)
    targets = torch.tensor([[1.0], [-2.0], [0.5]], dtype=DTYPE)
    policy = RBFPolicy(2, 1, 3, support_points=support, targets=targets)
    torch.testing.assert_close(policy(support), targets / (1 + POLICY_NOISE_VARIANCE), atol=1e-4, rtol=0)


def test_squash_is_bounded_and_matches_formula():
    z = torch.linspace(-10, 10, 1001, dtype=DTYPE)[:, None]
    bound = torch.tensor([2.5], dtype=DTYPE)
    u = sin_squash(z, bound)
    torch.testing.assert_close(u, 2.5 * (9 * torch.sin(z) + torch.sin(3 * z)) / 8)
    assert u.abs().max() <= 2.5 + 1e-12
    assert torch.isclose(sin_squash(torch.tensor([torch.pi / 2], dtype=DTYPE), bound), bound).all()


@pytest.mark.parametrize(("kind", "scale"), list(itertools.product(EXACT_KINDS, [0.3, 1.5])))
def test_moments_against_monte_carlo(mc, cov_factory, kind, scale, engine):
    policy = make_policy(kind)
    gen = torch.Generator().manual_seed(int(10 * scale))
    state = Gaussian(0.5 * torch.randn(3, generator=gen, dtype=DTYPE), cov_factory(3, scale, gen))
    with torch.no_grad():
        result = policy.moments(state, engine)
        x = state.sample(NUM_SAMPLES, generator=gen)
        mc.assert_moments(result, x, policy(x))
    torch.testing.assert_close(state.cov @ result.gain, result.cross_cov)


@pytest.mark.parametrize("scale", [0.3, 1.5])
def test_squashed_rbf_moments_approximately(cov_factory, scale, engine):
    policy = make_policy("squashed-rbf")
    gen = torch.Generator().manual_seed(int(10 * scale))
    state = Gaussian(0.5 * torch.randn(3, generator=gen, dtype=DTYPE), cov_factory(3, scale, gen))
    with torch.no_grad():
        result = policy.moments(state, engine)
        x = state.sample(NUM_SAMPLES, generator=gen)
        u = policy(x)
    u_c, x_c = u - u.mean(0), x - x.mean(0)
    assert ((result.mean - u.mean(0)).abs() <= APPROX_MEAN_TOL * u.std(0)).all()
    for analytic, sampled in ((result.cov, u_c.T @ u_c / len(u)), (result.cross_cov, x_c.T @ u_c / len(u))):
        assert torch.linalg.norm(analytic - sampled) <= APPROX_COV_TOL * torch.linalg.norm(sampled)


@pytest.mark.parametrize("scale", [0.2, 1.0, 3.0])
def test_squash_moments_against_monte_carlo(mc, cov_factory, scale, engine):
    gen = torch.Generator().manual_seed(7)
    state = Gaussian(torch.tensor([0.3, -1.2], dtype=DTYPE), cov_factory(2, scale, gen))
    bound = torch.tensor([10.0, 0.5], dtype=DTYPE)
    z = state.sample(NUM_SAMPLES, generator=gen)
    mc.assert_moments(sin_squash_moments(state, bound, engine), z, sin_squash(z, bound))


@pytest.mark.parametrize("kind", KINDS)
def test_delta_input_gives_deterministic_action(kind, engine):
    policy = make_policy(kind)
    x = torch.tensor([0.2, -0.3, 0.8], dtype=DTYPE)
    with torch.no_grad():
        result = policy.moments(Gaussian(x, torch.zeros(3, 3, dtype=DTYPE)), engine)
        torch.testing.assert_close(result.mean, policy(x))
    assert result.cov.abs().max() < 1e-12


@pytest.mark.parametrize("kind", KINDS)
def test_batched_equals_per_item(kind, cov_factory, engine):
    policy = make_policy(kind)
    gen = torch.Generator().manual_seed(5)
    means = torch.randn(4, 3, generator=gen, dtype=DTYPE)
    covs = cov_factory(3, 0.8, gen, batch=(4,))
    with torch.no_grad():
        batched = policy.moments(Gaussian(means, covs), engine)
        for i in range(4):
            single = policy.moments(Gaussian(means[i], covs[i]), engine)
            torch.testing.assert_close(batched.mean[i], single.mean)
            torch.testing.assert_close(batched.cov[i], single.cov)
            torch.testing.assert_close(batched.gain[i], single.gain)


@pytest.mark.parametrize("kind", KINDS)
def test_gradcheck_wrt_input_and_psi(kind, engine):
    policy = make_policy(kind)
    names = [name for name, _ in policy.named_parameters()]
    gen = torch.Generator().manual_seed(6)
    mean = torch.randn(3, generator=gen, dtype=DTYPE, requires_grad=True)
    root = (0.5 * torch.randn(3, 3, generator=gen, dtype=DTYPE)).requires_grad_()
    psi = tuple(p.detach().clone().requires_grad_() for p in policy.parameters())

    def moments(m, r, *params):
        state = Gaussian(m, r @ r.T)
        out = torch.func.functional_call(
            _Moments(policy, engine), {f"policy.{n}": p for n, p in zip(names, params, strict=True)}, (state,)
        )
        return out.mean, out.cov, out.cross_cov

    assert torch.autograd.gradcheck(moments, (mean, root, *psi))


@pytest.mark.parametrize("kind", KINDS)
def test_gradcheck_deterministic_action(kind):
    policy = make_policy(kind)
    names = [name for name, _ in policy.named_parameters()]
    x = torch.randn(4, 3, generator=torch.Generator().manual_seed(8), dtype=DTYPE).requires_grad_()
    psi = tuple(p.detach().clone().requires_grad_() for p in policy.parameters())

    def act(inputs, *params):
        return torch.func.functional_call(policy, dict(zip(names, params, strict=True)), (inputs,))

    assert torch.autograd.gradcheck(act, (x, *psi))


class _Moments(torch.nn.Module):
    """Wraps a policy's moment map as a forward, so functional_call can swap ψ."""

    def __init__(self, policy, engine):
        super().__init__()
        self.policy, self.engine = policy, engine

    def forward(self, state):
        return self.policy.moments(state, self.engine)


def test_rbf_psi_is_the_paper_parameters():
    names = {name for name, _ in make_rbf().named_parameters()}
    assert names == {"support_points", "targets", "log_lengthscales"}
    assert {name for name, _ in SquashedPolicy(make_rbf(), 1.0).named_parameters()} == {f"policy.{n}" for n in names}


@pytest.mark.parametrize("moments", FORMULATIONS)
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(1e-3, 5.0), kind=st.sampled_from(KINDS))
def test_covariances_are_psd(psd, cov_factory, seed, scale, kind, moments):
    gen = torch.Generator().manual_seed(seed)
    policy = make_policy(kind, seed=seed % 7)
    state = Gaussian(2 * torch.randn(3, generator=gen, dtype=DTYPE), cov_factory(3, scale, gen))
    with torch.no_grad():
        result = policy.moments(state, Engine(moments=moments))
    psd(result.cov)
    joint = torch.cat(
        [torch.cat([state.cov, result.cross_cov], -1), torch.cat([result.cross_cov.T, result.cov], -1)],
        -2,
    )
    psd(joint)


def test_rejects_bad_shapes():
    with pytest.raises(ValueError):
        RBFPolicy(3, 1, 4, support_points=torch.zeros(4, 2, dtype=DTYPE))
    with pytest.raises(ValueError):
        LinearPolicy(3, 1, weight=torch.zeros(3, 1, dtype=DTYPE))
    with pytest.raises(ValueError):
        SquashedPolicy(make_rbf(), [1.0, -1.0])


# --- The fused formulation against the reference one (qtl.kernels.Engine), values and gradients. ---


@pytest.mark.parametrize(("num", "batch", "scale"), list(itertools.product([1, 2, 3], [(), (3,), (2, 3)], [0.3, 2.0])))
def test_squash_moments_formulations_agree(num, batch, scale):
    mean, root = random_state(num, batch, seed=num + 10 * len(batch), scale=scale)
    bound = torch.linspace(0.5, 3.0, num, dtype=DTYPE).requires_grad_()

    def moments(engine, m, r, b):
        out = sin_squash_moments(Gaussian(m, r @ r.mT), b, engine)
        return out.mean, out.cov, out.cross_cov, out.gain

    assert_formulations_agree(moments, (mean, root, bound))


@pytest.mark.parametrize(("inner", "restarts"), list(itertools.product(["rbf", "linear"], [1, 3])))
def test_squashed_policy_moments_formulations_agree(inner, restarts):
    """SquashedPolicy's fused chaining equals compose(inner, squash) of the reference, in value and in ∂/∂ψ."""
    policy = SquashedPolicy(make_policy(inner), [2.0, 0.5])
    if restarts > 1:
        policy = spread_restarts(policy, restarts)
    mean, root = random_state(3, (restarts,) if restarts > 1 else (), seed=restarts)

    def moments(engine, m, r, *psi):
        out = policy.prepare(engine)(Gaussian(m, r @ r.mT))
        return out.mean, out.cov, out.cross_cov, out.gain

    assert_formulations_agree(moments, (mean, root, *policy.parameters()))


@pytest.mark.parametrize("kind", ["rbf", "squashed-rbf", "linear"])
def test_actions_map_equals_forward_bit_for_bit(kind):
    """actions() computes ψ-only quantities once (RBF: β_π) and then acts exactly as forward, batched ψ too."""
    policy = make_policy(kind)
    x = torch.randn(7, policy.input_dim, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    assert torch.equal(policy.actions()(x), policy(x))
    batched = batched_policy(policy, 3)
    xb = torch.randn(3, 7, policy.input_dim, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    assert torch.equal(batched.actions()(xb), batched(xb))
    if kind != "linear":  # β_π is solved once: the map keeps ψ's values of the moment it was made
        act = policy.actions()
        before = act(x)
        with torch.no_grad():
            next(p for n, p in policy.named_parameters() if n.endswith("targets")).add_(1.0)
        assert torch.equal(act(x), before) and not torch.equal(policy(x), before)
