"""RBF network with free weights (MC-PILCO's sum of Gaussians) and its factory: values, moments, gradients, dropout."""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from qtl.features import AngleFeatures
from qtl.gaussian import Gaussian
from qtl.kernels.engine import Engine
from qtl.policies import (
    LinearPolicy,
    RBFNetwork,
    RBFPolicy,
    SquashedPolicy,
    rbf_network_policy,
    restart_state,
)
from tests.propagation.restarts import RESTARTS, spread_restarts

DTYPE = torch.float64
NUM_SAMPLES = 100_000
# Dropout draws per point for the unbiasedness check (each draw one independent set of masks).
DROPOUT_DRAWS = 20_000
# Batched and per-restart actions differ only by the order of floating-point operations.
RTOL, ATOL = 1e-10, 1e-13


def make_network(input_dim: int = 3, output_dim: int = 2, num_basis: int = 7, seed: int = 0) -> RBFNetwork:
    """A small network with random centres `N x D`, weights `N x F` and length-scales `F x D` in (0.6, 1.4)."""
    gen = torch.Generator().manual_seed(seed)
    return RBFNetwork(
        torch.randn(num_basis, input_dim, generator=gen, dtype=DTYPE),
        torch.randn(num_basis, output_dim, generator=gen, dtype=DTYPE),
        0.6 + 0.8 * torch.rand(output_dim, input_dim, generator=gen, dtype=DTYPE),
    )


def direct(net: RBFNetwork, x: Tensor) -> Tensor:
    """π̃(x)_f = Σ_n w_nf exp(−½ Σ_d ((x_d − c_nd)/ℓ_fd)²), point by point and basis by basis: `S x F`."""
    c, w, ls = net.centres.detach(), net.weights.detach(), net.lengthscales.detach()
    out = torch.zeros(x.shape[0], net.output_dim, dtype=x.dtype)
    for s in range(x.shape[0]):
        for f in range(net.output_dim):
            for n in range(net.num_basis):
                out[s, f] += w[n, f] * math.exp(-0.5 * float((((x[s] - c[n]) / ls[f]) ** 2).sum()))
    return out


def test_forward_is_the_sum_of_gaussians():
    net = make_network()
    x = torch.randn(6, 3, generator=torch.Generator().manual_seed(1), dtype=DTYPE)
    with torch.no_grad():
        torch.testing.assert_close(net(x), direct(net, x), rtol=1e-12, atol=1e-14)
        at_centre = RBFNetwork(net.centres[:1].clone(), torch.ones(1, 2, dtype=DTYPE), net.lengthscales.clone())
        torch.testing.assert_close(at_centre(net.centres[:1]), torch.ones(1, 2, dtype=DTYPE))  # exp(0) · 1


def test_psi_is_centres_weights_and_log_lengthscales():
    net = make_network()
    assert {name for name, _ in net.named_parameters()} == {"centres", "weights", "log_lengthscales"}
    assert net.dropout == 0.0


@pytest.mark.parametrize(("moments", "scale"), [("reference", 0.3), ("reference", 1.2), ("fused", 0.3), ("fused", 1.2)])
def test_prepare_moments_against_monte_carlo(mc, cov_factory, moments, scale):
    """``prepare()`` (PILCO gp2) against samples of ``forward``: within 5 Monte Carlo standard errors (conftest)."""
    net = make_network()
    gen = torch.Generator().manual_seed(int(10 * scale))
    state = Gaussian(0.5 * torch.randn(3, generator=gen, dtype=DTYPE), cov_factory(3, scale, gen))
    with torch.no_grad():
        result = net.prepare(Engine(moments=moments))(state)
        x = state.sample(NUM_SAMPLES, generator=gen)
        mc.assert_moments(result, x, net(x, Engine(moments=moments)))


def test_moments_ignore_dropout():
    """Dropout acts in ``forward`` only: the moment map is the same with it set."""
    net = make_network()
    state = Gaussian(torch.tensor([0.1, -0.2, 0.3], dtype=DTYPE), 0.2 * torch.eye(3, dtype=DTYPE))
    with torch.no_grad():
        plain = net.moments(state)
        net.set_dropout(0.5, torch.Generator().manual_seed(0))
        dropped = net.moments(state)
    for a, b in zip((plain.mean, plain.cov, plain.cross_cov), (dropped.mean, dropped.cov, dropped.cross_cov),
                    strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("rate", [0.0, 0.3])
@pytest.mark.parametrize("moments", ["reference", "fused"])
def test_gradcheck_forward_wrt_input_and_all_psi(moments, rate):
    """Finite differences (float64) of both forms, dropout included (the same masks at every evaluation)."""
    net = make_network(num_basis=4)
    names = [name for name, _ in net.named_parameters()]
    x = torch.randn(5, 3, generator=torch.Generator().manual_seed(2), dtype=DTYPE).requires_grad_()
    psi = tuple(p.detach().clone().requires_grad_() for p in net.parameters())

    def act(inputs: Tensor, *params: Tensor) -> Tensor:
        net.set_dropout(rate, torch.Generator().manual_seed(3))  # one mask for every evaluation
        return torch.func.functional_call(net, dict(zip(names, params, strict=True)), (inputs, Engine(moments=moments)))

    assert torch.autograd.gradcheck(act, (x, *psi))


@pytest.mark.parametrize("rate", [0.0, 0.25])
@pytest.mark.parametrize(("output_dim", "shape"), [(1, (400, 5)), (2, (2, 3, 5))])
def test_fused_forward_equals_the_reference(output_dim, shape, rate):
    """The fused op (one autograd node) gives the reference's actions and gradients for x and ψ, to round-off."""
    net = make_network(input_dim=5, output_dim=output_dim, num_basis=23, seed=4)
    gen = torch.Generator().manual_seed(5)
    x = torch.randn(*shape, generator=gen, dtype=DTYPE)
    probe = torch.randn(*shape[:-1], output_dim, generator=gen, dtype=DTYPE)
    results = []
    for moments in ("reference", "fused"):
        net.set_dropout(rate, torch.Generator().manual_seed(6))  # the same masks in both
        point = x.clone().requires_grad_()
        actions = net(point, Engine(moments=moments))
        grads = torch.autograd.grad((actions * probe).sum(), (point, *net.parameters()))
        results.append((actions, *grads))
    for got, want in zip(results[1], results[0], strict=True):
        torch.testing.assert_close(got, want, rtol=RTOL, atol=ATOL * want.abs().max().item())
    assert rate == 0.0 or (results[0][0] == 0).sum() < results[0][0].numel()  # masks kept some bases


def graph_nodes(t: Tensor) -> str:
    """The names of the autograd nodes within three steps of ``t``."""
    names, nodes = [], [t.grad_fn]
    for _ in range(3):
        names += [node.name() for node in nodes if node is not None]
        nodes = [nxt for node in nodes if node is not None for nxt, _ in node.next_functions]
    return " ".join(names)


def test_the_reference_form_turns_the_fused_op_off():
    """With ``Engine.network="reference"`` the fused formulation's actions are the plain form's, bit for bit."""
    net = make_network(input_dim=5, output_dim=1, num_basis=9)
    x = torch.randn(7, 5, generator=torch.Generator().manual_seed(8), dtype=DTYPE)
    plain = net(x, Engine(moments="reference"))
    pinned = Engine(moments="fused", network="reference")
    assert torch.equal(net(x, pinned), plain) and "_NetworkValues" not in graph_nodes(net(x, pinned))
    assert "_NetworkValuesBackward" in graph_nodes(net(x, Engine(moments="fused")))


def test_fused_forward_skips_the_gradients_nobody_needs():
    """Points without gradient (a rollout's start) and frozen ψ: the fused op's backward forms only what is asked."""
    net = make_network(input_dim=5, output_dim=1, num_basis=9)
    x = torch.randn(7, 5, generator=torch.Generator().manual_seed(8), dtype=DTYPE)
    net.centres.requires_grad_(False)
    net(x, Engine(moments="fused")).sum().backward()
    reference = torch.autograd.grad(net(x, Engine(moments="reference")).sum(), net.weights)[0]
    assert net.centres.grad is None and net.weights.grad is not None
    torch.testing.assert_close(net.weights.grad, reference, rtol=RTOL, atol=ATOL)


# -- dropout ------------------------------------------------------------------------------------------


def test_dropout_masks_differ_between_calls_and_follow_the_generator():
    net = make_network()
    x = torch.randn(8, 3, generator=torch.Generator().manual_seed(3), dtype=DTYPE)
    with torch.no_grad():
        clean = net(x)
        net.set_dropout(0.3, torch.Generator().manual_seed(5))
        first, second = net(x), net(x)
        net.set_dropout(0.3, torch.Generator().manual_seed(5))
        again = net(x)
        net.set_dropout(0.3, torch.Generator().manual_seed(6))
        other = net(x)
    assert not torch.equal(first, second) and not torch.equal(first, clean)
    assert torch.equal(first, again)  # the same seed gives the same masks
    assert not torch.equal(first, other)


def test_dropout_is_unbiased(mc):
    """E over masks of the dropped-out actions is the plain network's action (each kept basis scaled by 1/(1 − p))."""
    net = make_network()
    x = torch.randn(4, 3, generator=torch.Generator().manual_seed(4), dtype=DTYPE)
    with torch.no_grad():
        clean = net(x)
        net.set_dropout(0.25, torch.Generator().manual_seed(7))
        draws = net(x.expand(DROPOUT_DRAWS, 4, 3))  # DROPOUT_DRAWS x 4 x 2, masks independent per point
    assert draws.std(0).min() > 0.01  # the masks really vary
    mc.assert_mean(clean, draws, "dropout mean")


def test_one_basis_is_kept_scaled_or_dropped_with_probability_p():
    """With one basis function each action is either 0 (dropped) or w k(x)/(1 − p) (kept), dropped a fraction ≈ p."""
    rate, points = 0.3, 20_000
    net = make_network(num_basis=1)
    x = torch.randn(points, 3, generator=torch.Generator().manual_seed(8), dtype=DTYPE)
    with torch.no_grad():
        full = net(x)
        net.set_dropout(rate, torch.Generator().manual_seed(9))
        dropped = net(x)
    zero = dropped == 0
    torch.testing.assert_close(dropped[~zero], (full / (1 - rate))[~zero], rtol=1e-14, atol=0)
    fraction = zero[:, 0].double().mean().item()
    assert abs(fraction - rate) <= 5 * math.sqrt(rate * (1 - rate) / points)  # binomial: 5 standard errors


def test_dropout_masks_are_shared_by_the_action_dimensions():
    """Equal length-scales and weights w_2 = 2 w_1: u_2 = 2 u_1 exactly only if both actions drop the same bases."""
    gen = torch.Generator().manual_seed(10)
    weights = torch.randn(9, 1, generator=gen, dtype=DTYPE)
    net = RBFNetwork(torch.randn(9, 3, generator=gen, dtype=DTYPE), torch.cat([weights, 2 * weights], -1),
                     torch.ones(2, 3, dtype=DTYPE))
    x = 0.5 * torch.randn(50, 3, generator=gen, dtype=DTYPE)
    with torch.no_grad():
        clean = net(x)
        net.set_dropout(0.5, torch.Generator().manual_seed(11))
        u = net(x)
    assert not torch.allclose(u, clean)
    torch.testing.assert_close(u[:, 1], 2 * u[:, 0], rtol=1e-13, atol=1e-15)


def test_rate_zero_is_exactly_the_plain_network():
    net = make_network()
    x = torch.randn(6, 3, generator=torch.Generator().manual_seed(12), dtype=DTYPE)
    with torch.no_grad():
        clean = net(x)
        net.set_dropout(0.0, torch.Generator().manual_seed(0))
        assert torch.equal(net(x), clean)
        net.set_dropout(0.4, torch.Generator().manual_seed(0))
        net.set_dropout(0.0)  # switched off again
        assert torch.equal(net(x), clean) and net.dropout == 0.0


@pytest.mark.parametrize("rate", [-0.1, 1.0, 1.5])
def test_bad_dropout_rates_are_refused(rate):
    with pytest.raises(ValueError, match=r"dropout rate must be in \[0, 1\)"):
        make_network().set_dropout(rate)


def test_squashed_network_delegates_dropout():
    net = make_network()
    squashed = SquashedPolicy(net, [2.0, 0.5])
    x = torch.randn(6, 3, generator=torch.Generator().manual_seed(13), dtype=DTYPE)
    with torch.no_grad():
        clean = squashed(x)
        squashed.set_dropout(0.3, torch.Generator().manual_seed(1))
        assert net.dropout == 0.3
        assert not torch.equal(squashed(x), clean)
        squashed.set_dropout(0.0)
        assert net.dropout == 0.0 and torch.equal(squashed(x), clean)


@pytest.mark.parametrize("policy", [
    RBFPolicy(3, 2, 4, generator=torch.Generator().manual_seed(0)),
    LinearPolicy(3, 2, generator=torch.Generator().manual_seed(0)),
    SquashedPolicy(RBFPolicy(3, 2, 4, generator=torch.Generator().manual_seed(0)), 1.0),
], ids=["rbf", "linear", "squashed-rbf"])
def test_policies_without_dropout_refuse_a_rate_but_accept_zero(policy):
    with pytest.raises(ValueError, match="has no dropout"):
        policy.set_dropout(0.1)
    policy.set_dropout(0.0)  # what the search does after a run: no error


@pytest.mark.parametrize("input_shape", [(5, 3), (RESTARTS, 5, 3)])
def test_batched_actions_equal_per_restart(input_shape):
    """ψ `R x ...` (restarts searched together) acts as R networks, on shared or per-restart features."""
    batched = spread_restarts(make_network())
    x = torch.randn(input_shape, generator=torch.Generator().manual_seed(14), dtype=DTYPE)
    with torch.no_grad():
        actions = batched(x)
        assert actions.shape == (RESTARTS, 5, 2)
        for r in range(RESTARTS):
            single = make_network()
            single.load_state_dict(restart_state(batched, r))
            torch.testing.assert_close(actions[r], single(x[r] if x.dim() == 3 else x), rtol=RTOL, atol=ATOL)
        assert not torch.allclose(actions[0], actions[1])  # the restarts really differ


def test_rejects_mismatched_shapes_and_bad_lengthscales():
    with pytest.raises(ValueError, match="must agree"):
        RBFNetwork(torch.zeros(4, 3, dtype=DTYPE), torch.zeros(5, 2, dtype=DTYPE), torch.ones(2, 3, dtype=DTYPE))
    with pytest.raises(ValueError, match="must agree"):
        RBFNetwork(torch.zeros(4, 3, dtype=DTYPE), torch.zeros(4, 2, dtype=DTYPE), torch.ones(2, 2, dtype=DTYPE))
    with pytest.raises(ValueError, match="lengthscales must be positive"):
        RBFNetwork(torch.zeros(4, 3, dtype=DTYPE), torch.zeros(4, 2, dtype=DTYPE), torch.zeros(2, 3, dtype=DTYPE))


# -- the factory (policy=rbf_network) -----------------------------------------------------------------

# A cart-pole-like state: [x, ẋ, θ, θ̇], features [x, ẋ, θ̇, sin θ, cos θ].
CARTPOLE_FEATURES = AngleFeatures(4, (2,))


def network_policy(seed: int = 0, **kwargs: float) -> RBFNetwork:
    """``rbf_network_policy`` on the cart-pole features, 500 bases, 1 action."""
    return rbf_network_policy(5, 1, num_basis=500, start_features=torch.zeros(10, 5, dtype=DTYPE),
                              features=CARTPOLE_FEATURES, generator=torch.Generator().manual_seed(seed), **kwargs)


def test_factory_spreads_centres_over_the_states_and_angles_over_the_circle():
    net = network_policy(centre_range=1.0, weight_range=0.3, lengthscale=0.7)
    centres = net.centres.detach()
    assert centres.shape == (500, 5)
    assert centres[:, :3].abs().max() <= 1.0  # x, ẋ, θ̇ uniform in ±centre_range
    assert centres[:, :3].abs().max() > 0.9  # ... spread over it
    torch.testing.assert_close(centres[:, 3].square() + centres[:, 4].square(), torch.ones(500, dtype=DTYPE))
    # The angles fill [−π, π), not ±centre_range: cos θ < cos 1 (θ beyond ±1) for about 1 − 1/π of them.
    far = (centres[:, 4] < math.cos(1.0)).double().mean().item()
    assert abs(far - (1 - 1 / math.pi)) < 0.1
    assert (centres[:, 3] < 0).any() and (centres[:, 3] > 0).any()
    weights = net.weights.detach()
    assert weights.shape == (500, 1) and weights.abs().max() <= 0.3 and weights.abs().max() > 0.25
    torch.testing.assert_close(net.lengthscales.detach(), torch.full((1, 5), 0.7, dtype=DTYPE))


def test_factory_without_features_spreads_every_feature():
    net = rbf_network_policy(3, 2, num_basis=200, start_features=torch.zeros(1, 3, dtype=DTYPE), centre_range=2.0,
                             generator=torch.Generator().manual_seed(1))
    centres = net.centres.detach()
    assert centres.abs().max() <= 2.0 and centres.abs().max() > 1.8 and net.weights.shape == (200, 2)


def test_factory_is_the_generators_own():
    a, b, c = network_policy(3), network_policy(3), network_policy(4)
    for name, value in a.state_dict().items():
        assert torch.equal(value, b.state_dict()[name])
    assert not torch.equal(a.centres, c.centres) and not torch.equal(a.weights, c.weights)


@pytest.mark.parametrize("kwargs", [{"centre_range": 0.0}, {"centre_range": -1.0}, {"weight_range": -0.1},
                                    {"lengthscale": 0.0}])
def test_factory_refuses_bad_ranges(kwargs):
    with pytest.raises(ValueError, match="must be > 0"):
        network_policy(**kwargs)


def test_factory_refuses_features_of_another_dimension():
    with pytest.raises(ValueError, match="5-D features, the policy takes 4"):
        rbf_network_policy(4, 1, num_basis=3, start_features=torch.zeros(3, 4, dtype=DTYPE),
                           features=CARTPOLE_FEATURES)
