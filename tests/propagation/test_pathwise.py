"""Pathwise particles: Matheron samples against the exact posterior, one function per path, CRN, gradients."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from torch import Tensor

from qtl.build import build
from qtl.config import register_configs
from qtl.errors import UserError
from qtl.features import AngleFeatures
from qtl.gaussian import Gaussian
from qtl.kernels.engine import Engine
from qtl.models import DynamicsGP, GPPosteriorCache, SparseDynamicsGP
from qtl.policies import RBFPolicy, SquashedPolicy
from qtl.propagation import Particles
from qtl.propagation.gp_cache import cache_tensors
from qtl.propagation.noise import PATHWISE_STREAM
from qtl.propagation.noise import draw_seed as _draw_seed
from qtl.propagation.pathwise import FeatureDraw, MatheronPaths, draw_features, matheron_paths, path_values
from tests.conftest import make_gp
from tests.helpers import (
    gradcheck_value_wrt_policy_and_start,
    quadratic_reward,
    squashed_rbf_parts,
    tiny_config,
)
from tests.propagation.restarts import assert_restarts_equal_separate
from tests.test_build import factory_keywords

DTYPE = torch.float64
# Agreement with an independent per-particle reference using the same random numbers.
EXACT_RTOL, EXACT_ATOL = 1e-9, 1e-12


def scaled(cache: GPPosteriorCache) -> tuple[Tensor, Tensor, Tensor]:
    """The cache's training inputs over ℓ `E x n x D`, their squared norms `E x n`, and 1/ℓ `E x 1 x D`."""
    inv_ls = cache.hyperparameters.lengthscales.reciprocal()[:, None, :]
    data = cache.inputs * inv_ls
    return data, data.square().sum(-1), inv_ls


def draw_paths(cache: GPPosteriorCache, num_paths: int, num_features: int, seeds: Sequence[int],
               sparse_update: bool = True) -> MatheronPaths:
    """``num_paths`` Matheron functions per output of ``cache``'s GP per seed, draws stacked: `S x ...`.

    A sparse GP's cache gets its own update, or with ``sparse_update=False`` the exact one.
    """
    theta = cache.hyperparameters
    data, _, _ = scaled(cache)
    num_outputs, num_points, input_dim = data.shape
    draws = [draw_features(torch.Generator().manual_seed(seed), num_outputs, input_dim, num_points, num_paths,
                           num_features) for seed in seeds]
    draw = FeatureDraw(*(torch.stack(parts) for parts in zip(*draws, strict=True)))
    factors = {"prior_inv": cache.prior_inv, "update_root": cache.update_root} if sparse_update else {}
    return matheron_paths(draw, data, cache.beta, cache.K_inv, theta.signal_variance, theta.noise_variance,
                          **factors)


def values_at(cache: GPPosteriorCache, paths: MatheronPaths, points: Tensor) -> Tensor:
    """Every drawn function at each of ``points`` `m x D`: `S x P x E x m`."""
    data, data_sq, inv_ls = scaled(cache)
    num_paths = paths.update.shape[-2]
    columns = [path_values((x * inv_ls).expand(-1, num_paths, -1), data, data_sq,
                           cache.hyperparameters.signal_variance, paths) for x in points]  # each E x P
    return torch.stack(columns, dim=-1).transpose(-3, -2)


def se_kernel(cache: GPPosteriorCache, a: Tensor, b: Tensor) -> Tensor:
    """The GP's SE kernel between ``a`` `m x D` and ``b`` `k x D` per output: `E x m x k` (Eq. 3)."""
    theta = cache.hyperparameters
    ls = theta.lengthscales[:, None, :]
    sq = ((a / ls)[:, :, None, :] - (b / ls)[:, None, :, :]).square().sum(-1)
    return theta.signal_variance[:, None, None] * torch.exp(-0.5 * sq)


def exact_posterior(cache: GPPosteriorCache, points: Tensor) -> tuple[Tensor, Tensor]:
    """The latent posterior mean `E x m` and covariance `E x m x m` at ``points`` `m x D`."""
    cross = se_kernel(cache, points, cache.inputs)  # E x m x n
    mean = (cross @ cache.beta[..., None]).squeeze(-1)
    cov = se_kernel(cache, points, points) - cross @ cache.K_inv @ cross.mT
    return mean, cov


def centred_products(values: Tensor, mean: Tensor) -> Tensor:
    """(f − m)(f − m)ᵀ per drawn function, about the known mean ``mean`` `E x m`: `P x E x m x m`."""
    centred = values - mean
    return centred[..., :, None] * centred[..., None, :]


def test_one_draw_has_the_feature_kernels_posterior_moments(gp_factory, mc):
    # Given one draw's frequencies and phases, f_p(Z) − m(Z) = A w_p − σ k(Z, X) K⁻¹ ε_p with
    # A = Φ(Z) − k(Z, X) K⁻¹ Φ(X): the functions' mean is the posterior mean k β and their covariance
    # A Aᵀ + σ² k K⁻¹ K⁻¹ kᵀ (the posterior of the features' kernel). Within MC error of P functions.
    gp = gp_factory(30, 2, 1, seed=11)
    cache = gp.posterior_cache()
    theta = cache.hyperparameters
    points = torch.tensor([[0.1, -0.2, 0.3], [0.5, 0.4, -0.6], [0.12, -0.18, 0.25], [3.0, 3.0, 3.0]], dtype=DTYPE)
    paths = draw_paths(cache, 40_000, 32, seeds=[3])
    values = values_at(cache, paths, points)[0]  # P x E x m
    paths = MatheronPaths(*(t[0] for t in paths))
    mean, _ = exact_posterior(cache, points)
    data, _, inv_ls = scaled(cache)
    scale = (2 * theta.signal_variance / 32).sqrt()[:, None, None]
    phi_z = scale * torch.cos((points * inv_ls) @ paths.frequencies.mT + paths.phases[:, None, :])  # E x m x L
    phi_x = scale * torch.cos(data @ paths.frequencies.mT + paths.phases[:, None, :])  # E x n x L
    cross = se_kernel(cache, points, cache.inputs) @ cache.K_inv  # k(Z, X) K⁻¹: E x m x n
    a = phi_z - cross @ phi_x
    cov = a @ a.mT + theta.noise_variance[:, None, None] * cross @ cross.mT
    mc.assert_mean(mean, values, "mean")
    mc.assert_mean(cov, centred_products(values, mean), "covariance given the features")


def test_drawn_functions_converge_to_the_exact_posterior(gp_factory, mc):
    # The Matheron covariance is linear in the features' kernel Φ Φᵀ, whose mean over frequencies and
    # phases is the SE kernel: so over draws the functions' mean and covariance are the exact GP
    # posterior's, for any L. Functions of one draw share their features, so the i.i.d. units are
    # the draws: each draw's sample moments (about the exact mean) are one term of the MC check.
    gp = gp_factory(30, 2, 1, seed=12)
    cache = gp.posterior_cache()
    points = torch.tensor([[0.1, -0.2, 0.3], [0.5, 0.4, -0.6], [0.12, -0.18, 0.25], [-1.0, 0.8, 0.0]], dtype=DTYPE)
    mean, cov = exact_posterior(cache, points)
    values = values_at(cache, draw_paths(cache, 200, 64, seeds=range(300)), points)  # 300 draws x 200 x E x m
    mc.assert_mean(mean, values.mean(1), "mean over draws")
    mc.assert_mean(cov, centred_products(values, mean).mean(1), "covariance over draws")


def test_one_draw_with_many_features_is_close_to_the_exact_posterior(gp_factory):
    # One draw (shared features) at L = 4096: its covariance differs from the exact posterior's by
    # the features' kernel error, O(α² √(2/L)) ≈ 0.02 α² per entry, and by MC error (2000 functions).
    gp = gp_factory(30, 2, 1, seed=13)
    cache = gp.posterior_cache()
    points = torch.tensor([[0.1, -0.2, 0.3], [0.5, 0.4, -0.6], [-1.0, 0.8, 0.0]], dtype=DTYPE)
    mean, cov = exact_posterior(cache, points)
    values = values_at(cache, draw_paths(cache, 2000, 4096, seeds=[5]), points)[0]
    alpha2 = cache.hyperparameters.signal_variance[:, None]
    assert ((values.mean(0) - mean).abs() <= 0.1 * alpha2.sqrt()).all()
    features_error = 4 * alpha2[..., None] * (2 / 4096) ** 0.5
    mc_error = 4 * cov.diagonal(dim1=-2, dim2=-1).amax(-1)[:, None, None] / 2000**0.5  # ~4 SE of a (co)variance
    tolerance = features_error + mc_error
    assert ((centred_products(values, mean).mean(0) - cov).abs() <= tolerance).all()


def test_the_update_vanishes_where_there_are_no_data(gp_factory):
    # Far from the data k(x, X) ≈ 0: the function is its prior sample, and Φ(x)ᵀ w with w ~ N(0, I)
    # has variance ≈ α² across functions (the prior), not the small posterior variance near data.
    gp = gp_factory(30, 2, 1, seed=14)
    cache = gp.posterior_cache()
    values = values_at(cache, draw_paths(cache, 5000, 2048, seeds=[1]), torch.full((1, 3), 50.0, dtype=DTYPE))[0]
    ratio = values.var(0).squeeze(-1) / cache.hyperparameters.signal_variance
    assert ((ratio > 0.85) & (ratio < 1.15)).all(), ratio


def pendulum_parts(gp_factory, num_basis: int = 8):
    """A 3-D state with an angle, a squashed RBF policy: PILCO's full configuration."""
    return squashed_rbf_parts(gp_factory, 3, (1,), num_basis, seeds=(22, 23))


def pathwise(gp, policy, reward, **kwargs) -> Particles:
    """Pathwise particles on the pendulum parts (angle dimension 1)."""
    settings = {"num_particles": 16, "num_features": 64, "seed": 3} | kwargs
    return Particles(gp, policy, reward, angle_dims=(1,), sampling="pathwise", **settings)


def reference_function(cache: GPPosteriorCache, paths: MatheronPaths, z: Tensor) -> Tensor:
    """f_p(z_p) = Σ_l α √(2/L) w_pl cos(ω_lᵀ (z_p/ℓ) + b_l) + Σ_i k(z_p, x_i) v_pi: `P x E` from ``z`` `P x D`."""
    inv_ls = cache.hyperparameters.lengthscales.reciprocal()  # E x D
    angle = torch.einsum("pd,eld->epl", z, paths.frequencies * inv_ls[:, None, :]) + paths.phases[:, None, :]
    prior = (paths.weights * torch.cos(angle)).sum(-1)  # E x P
    fitted = (se_kernel(cache, z, cache.inputs) * paths.update).sum(-1)  # E x P
    return (prior + fitted).T


@pytest.mark.parametrize("include_noise", [False, True])
def test_particles_follow_their_own_function(gp_factory, include_noise):
    # An independent reference with the propagator's functions and step noise gives the same paths:
    # each particle steps by its own function f_p at its state (+ independent σ_ε noise).
    gp, policy, reward = pendulum_parts(gp_factory)
    particles = pathwise(gp, policy, reward, include_noise=include_noise)
    start = Gaussian(torch.tensor([0.1, 2.5, -0.3], dtype=DTYPE), torch.diag(torch.tensor([0.04, 0.2, 0.09],
                                                                                         dtype=DTYPE)))
    horizon = 4
    cache = gp.posterior_cache()
    with torch.no_grad():
        states, actions = particles.trajectories(start, horizon)
        start_noise, step_noise, _ = particles.base_noise(horizon)
        paths = particles.functions()
        features = AngleFeatures(3, (1,))
        x = start.mean + start_noise @ torch.linalg.cholesky(start.cov).mT
        expected = [x]
        for t in range(horizon):
            u = policy(features(x))
            torch.testing.assert_close(actions[:, t], u, rtol=EXACT_RTOL, atol=EXACT_ATOL)
            x = x + reference_function(cache, paths, torch.cat([features(x), u], dim=-1))
            if include_noise:
                x = x + cache.hyperparameters.noise_variance.sqrt() * step_noise[t]
            expected.append(x)
    torch.testing.assert_close(states, torch.stack(expected, dim=1), rtol=EXACT_RTOL, atol=EXACT_ATOL)


def test_a_drawn_function_is_the_same_function_along_the_path(gp_factory):
    # A drawn function is a deterministic map: evaluated twice at one point it gives one value (by
    # the propagator's op and by the plain reference); the P functions differ from each other.
    gp, policy, reward = pendulum_parts(gp_factory)
    cache = gp.posterior_cache()
    particles = pathwise(gp, policy, reward, include_noise=False)
    paths = particles.functions()
    z = torch.tensor([[0.1, -0.2, 0.3, 0.95, 0.4]], dtype=DTYPE).expand(16, -1)
    first, second = reference_function(cache, paths, z), reference_function(cache, paths, z)
    assert torch.equal(first, second)
    data, data_sq, inv_ls = scaled(cache)
    at_z = path_values((z * inv_ls), data, data_sq, cache.hyperparameters.signal_variance, paths)
    assert torch.equal(at_z, path_values((z * inv_ls), data, data_sq, cache.hyperparameters.signal_variance, paths))
    torch.testing.assert_close(at_z.T, first, rtol=EXACT_RTOL, atol=EXACT_ATOL)
    assert first.std(0).min() > 0  # distinct functions per particle
    # From a point start (every particle at one state) the first step is f_p(x_0), whatever the
    # horizon asked for and whichever propagator of the same seed evaluates it.
    point = Gaussian(torch.tensor([0.1, 0.2, -0.3], dtype=DTYPE), torch.zeros(3, 3, dtype=DTYPE))
    with torch.no_grad():
        one = particles.trajectories(point, 1)[0][:, 1]
        later = pathwise(gp, policy, reward, include_noise=False).trajectories(point, 3)[0][:, 1]
    assert torch.equal(one, later)


def test_same_seed_same_rollout_and_draws(gp_factory):
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.zeros(3, dtype=DTYPE), 0.05 * torch.eye(3, dtype=DTYPE))
    value = pathwise(gp, policy, reward, seed=4).expected_return(start, 5)
    assert torch.equal(value, pathwise(gp, policy, reward, seed=4).expected_return(start, 5))
    assert not torch.equal(value, pathwise(gp, policy, reward, seed=5).expected_return(start, 5))
    # Pathwise adds a stream: the start and step noise are those of marginal sampling.
    marginal = Particles(gp, policy, reward, angle_dims=(1,), num_particles=16, seed=4)
    assert not torch.equal(value, marginal.expected_return(start, 5))
    noise, plain = pathwise(gp, policy, reward, seed=4).base_noise(5), marginal.base_noise(5)
    assert torch.equal(noise.start, plain.start) and torch.equal(noise.steps, plain.steps)
    with pytest.raises(ValueError, match="pathwise"):
        marginal.functions()


def test_resample_every_draws_new_functions(gp_factory):
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.zeros(3, dtype=DTYPE), 0.05 * torch.eye(3, dtype=DTYPE))
    particles = pathwise(gp, policy, reward, resample_every=2)
    values = [particles.expected_return(start, 3).detach() for _ in range(6)]
    for i, j in itertools.combinations(range(6), 2):
        assert torch.equal(values[i], values[j]) == (i // 2 == j // 2), (i, j)
    first, third = particles.functions(0), particles.functions(2)
    assert not torch.equal(first.frequencies, third.frequencies)
    assert torch.equal(first.update, particles.functions(0).update)
    fixed = pathwise(gp, policy, reward)
    assert len({float(fixed.expected_return(start, 3).detach()) for _ in range(3)}) == 1


@pytest.mark.parametrize(("expected_reward", "gaussian_resampling"), [(False, False), (True, True)])
def test_batched_restarts_equal_separate_rollouts(gp_factory, expected_reward, gaussian_resampling):
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.tensor([0.1, 0.2, -0.1], dtype=DTYPE), 0.01 * torch.eye(3, dtype=DTYPE))
    assert_restarts_equal_separate(
        lambda p: pathwise(gp, p, reward, num_particles=20, expected_reward=expected_reward,
                           gaussian_resampling=gaussian_resampling),
        policy, start, 5,
    )


def test_batched_starts_and_stacked_models_equal_per_item(gp_factory, cov_factory):
    gps = [gp_factory(30, 3, 1, (1,), seed=s) for s in (31, 32)]
    policy = SquashedPolicy(RBFPolicy(4, 1, 5, generator=torch.Generator().manual_seed(1)), 1.5)
    reward = quadratic_reward(3, (1,))
    stacked = pathwise([g.posterior_cache() for g in gps], policy, reward, num_particles=20)
    gen = torch.Generator().manual_seed(4)
    means = 0.3 * torch.randn(2, 1, 3, generator=gen, dtype=DTYPE)  # 2 starts x 2 models
    covs = cov_factory(3, 0.3, gen, batch=(2, 1))
    batched = stacked.rollout(Gaussian(means, covs), 4)
    assert batched.value.shape == (2, 2)
    for i, j in itertools.product(range(2), range(2)):
        expected = pathwise(gps[j], policy, reward, num_particles=20).rollout(Gaussian(means[i, 0], covs[i, 0]), 4)
        torch.testing.assert_close(batched.value[i, j], expected.value, rtol=1e-10, atol=0)
        torch.testing.assert_close(batched.states.cov[i, j], expected.states.cov, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize(("include_noise", "expected_reward"), [(False, False), (True, True)])
def test_gradcheck_rollout_wrt_policy_and_start(gp_factory, include_noise, expected_reward):
    gp = gp_factory(8, 2, 1, (1,), seed=41)
    policy = SquashedPolicy(RBFPolicy(3, 1, 3, generator=torch.Generator().manual_seed(2)), 1.0)
    particles = Particles(gp, policy, quadratic_reward(2, (1,)), angle_dims=(1,), num_particles=3, seed=1,
                          sampling="pathwise", num_features=16, include_noise=include_noise,
                          expected_reward=expected_reward)
    start = Gaussian(torch.tensor([0.1, 0.4], dtype=DTYPE), 0.05 * torch.eye(2, dtype=DTYPE))
    assert gradcheck_value_wrt_policy_and_start(policy, lambda s: particles.rollout(s, 3).value, start)


def test_expected_reward_without_noise_is_the_reward_of_the_drawn_state(gp_factory):
    # Given its function a noiseless pathwise step is deterministic: E[r(x_t) | x_{t−1}] = r(x_t).
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.tensor([0.1, 0.2, -0.1], dtype=DTYPE), 0.05 * torch.eye(3, dtype=DTYPE))
    values = [pathwise(gp, policy, reward, include_noise=False, expected_reward=e).rollout(start, 4).value
              for e in (False, True)]
    torch.testing.assert_close(values[1], values[0], rtol=1e-12, atol=1e-14)


def test_gradcheck_path_values_wrt_points(gp_factory):
    gp = gp_factory(10, 2, 1, seed=42)
    cache = gp.posterior_cache()
    paths = MatheronPaths(*(t[0] for t in draw_paths(cache, 4, 8, seeds=[2])))
    data, data_sq, _ = scaled(cache)
    z = torch.randn(2, 4, 3, generator=torch.Generator().manual_seed(1), dtype=DTYPE).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda z: path_values(z, data, data_sq, cache.hyperparameters.signal_variance, paths), (z,))


def test_float32_agrees_with_float64(gp_factory):
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.zeros(3, dtype=DTYPE), 0.05 * torch.eye(3, dtype=DTYPE))
    reference = pathwise(gp, policy, reward).rollout(start, 5)
    single = pathwise(gp, policy.to(torch.float32), reward, dtype=torch.float32).rollout(start, 5)
    assert single.value.dtype == torch.float32
    torch.testing.assert_close(single.value.double(), reference.value, rtol=1e-4, atol=1e-5)


def test_config_selects_pathwise_and_rejects_unknown_values(gp_factory):
    register_configs()
    gp, policy, reward = pendulum_parts(gp_factory)
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        default = compose(config_name="train", overrides=["propagation=particles"])
        chosen = compose(config_name="train", overrides=["propagation=particles", "propagation.sampling=pathwise",
                                                          "propagation.num_features=128"])
        unknown = compose(config_name="train", overrides=["propagation=particles", "propagation.sampling=exact"])
    built = instantiate(default.propagation)(gp, policy, reward, angle_dims=(1,))
    assert built.sampling == "marginal"  # nothing changes by default
    built = instantiate(chosen.propagation)(gp, policy, reward, angle_dims=(1,))
    assert (built.sampling, built.num_features) == ("pathwise", 128)
    assert built.functions().frequencies.shape == (3, 128, 5)
    with pytest.raises(UserError, match=r"propagation.sampling must be one of marginal, pathwise, got 'exact'"):
        instantiate(unknown.propagation)(gp, policy, reward, angle_dims=(1,))
    with pytest.raises(UserError, match="num_features"):
        Particles(gp, policy, reward, angle_dims=(1,), sampling="pathwise", num_features=0)


@pytest.mark.parametrize(
    ("override", "message"),
    [("propagation.sampling=exact", "propagation.sampling must be one of"),
     ("propagation.num_features=0", "num_features must be >= 1"),
     ("propagation.num_particles=1", "num_particles must be >= 2")],
)
def test_build_refuses_bad_particle_settings_before_any_work(override, message):
    """A bad particle setting is a one-line UserError from build(), before any episode runs."""
    with pytest.raises(UserError, match=message):
        build(tiny_config("propagation=particles", override))



def _sparse_gp(n: int = 60, inducing: int = 10, **kwargs) -> SparseDynamicsGP:
    """An SGPR on the toy data of ``make_gp`` with its θ (no fitting); ``kwargs`` e.g. its ``jitter``."""
    gp = make_gp(n, 2, 1, seed=12)
    inputs, targets = gp.train_inputs[0][0], gp.train_targets.mT  # `E x n x D` shared inputs, `E x n` targets
    return SparseDynamicsGP(inputs, targets, gp.hyperparameters, num_inducing=inducing,
                            generator=torch.Generator().manual_seed(0), **kwargs)


SPARSE_POINTS = torch.tensor([[0.1, -0.2, 0.3], [0.5, 0.4, -0.6], [-1.0, 0.8, 0.0], [0.12, -0.18, 0.25]],
                             dtype=DTYPE)


@pytest.mark.parametrize("jitter", [0.0, 1e-6, 0.05])
def test_sparse_gp_functions_converge_to_its_posterior(mc, jitter):
    # Wilson et al. 2020's sparse form: f̃ + k(·, Z) K_mm⁻¹ (u − f̃(Z) − ε̃), u ~ q(u), ε̃ ~ N(0, δI) with K_mm + δI
    # in K_mm's place. Over draws the functions' mean and covariance are the SGPR's predictive ones, k(·, Z) β and
    # k(·, ·) − k(·, Z) (K_mm⁻¹ − Σ⁻¹) k(Z, ·) (the model's own `predict`, checked equal here), within MC error of
    # 300 draws x 200 functions. A jitter of 0.05 α² moves the variances well past that error: leaving ε̃ out there
    # draws functions with 34-77 % of the model's variance (measured), and the test fails.
    model = _sparse_gp(jitter=jitter)
    cache = model.posterior_cache()
    mean, cov = exact_posterior(cache, SPARSE_POINTS)  # the cache's formula, at Z with K_mm⁻¹ − Σ⁻¹
    predicted_mean, predicted_var = model.predict(SPARSE_POINTS)
    torch.testing.assert_close(mean.mT, predicted_mean, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(cov.diagonal(dim1=-2, dim2=-1).mT, predicted_var, rtol=1e-8, atol=1e-12)
    values = values_at(cache, draw_paths(cache, 200, 64, seeds=range(300)), SPARSE_POINTS)
    mc.assert_mean(mean, values.mean(1), "mean over draws")
    mc.assert_mean(cov, centred_products(values, mean).mean(1), "covariance over draws")


def test_the_exact_update_on_a_sparse_cache_misstates_the_spread():
    # What the sparse factors are for: the exact update given the SGPR's cache (K_mm⁻¹ − Σ⁻¹ as if it were
    # (K + σ_ε²I)⁻¹) draws functions whose variance is off the model's (here larger at every point and output).
    cache = _sparse_gp().posterior_cache()
    mean, cov = exact_posterior(cache, SPARSE_POINTS)
    values = values_at(cache, draw_paths(cache, 200, 64, seeds=range(200), sparse_update=False), SPARSE_POINTS)
    variance = centred_products(values, mean).mean((0, 1)).diagonal(dim1=-2, dim2=-1)
    exact = cov.diagonal(dim1=-2, dim2=-1)
    assert (variance > exact).all() and (variance / exact).mean() > 1.2


def test_pathwise_particles_on_a_sparse_model_draw_its_functions(gp_factory):
    # The propagator passes the sparse factors on: its functions are matheron_paths' with them, and it rolls out.
    _, policy, reward = squashed_rbf_parts(gp_factory, 2, (), 5, (12, 1))
    model = _sparse_gp()
    particles = Particles(model, policy, reward, angle_dims=(), sampling="pathwise", num_features=32,
                          num_particles=16)
    cache = model.posterior_cache()
    data, _, _ = scaled(cache)
    draw = draw_features(torch.Generator().manual_seed(_draw_seed(particles.seed, 0, PATHWISE_STREAM)), 2, 3, 10, 16,
                         32)
    want = matheron_paths(draw, data, cache.beta, cache.K_inv, cache.hyperparameters.signal_variance,
                          cache.hyperparameters.noise_variance, prior_inv=cache.prior_inv,
                          update_root=cache.update_root)
    torch.testing.assert_close(particles.functions(0).update, want.update, rtol=0, atol=0)
    value = particles.rollout(Gaussian(torch.zeros(2, dtype=DTYPE), 0.01 * torch.eye(2, dtype=DTYPE)), 5, 0).value
    assert torch.isfinite(value)


def test_stacked_caches_must_be_of_one_kind(gp_factory):
    exact = gp_factory(10, 2, 1, seed=12).posterior_cache()
    sparse = _sparse_gp(inducing=10).posterior_cache()
    with pytest.raises(ValueError, match="kind"):
        cache_tensors([exact, sparse])


# -- path_dtype: the drawn functions evaluated in float32 within a float64 rollout ----------------------------

# Path values in float32 against float64, relative to the largest |f| of the batch: a few float32 ulp of the
# terms (tests/kernels/test_native_pathwise.py derives ~5e-6 of Σ|terms|), and here the terms do not cancel
# much (Σ|terms| ≲ 3 max|f| on these data).
PATH_F32_RTOL = 2e-5
# A whole rollout: each step's f carries the error above (~1e-6 of a step), which the 5 steps' dynamics
# (policy, angle features, Lipschitz constant of f ~ O(1)) carry into V and ∂V/∂ψ amplified by at most ~10
# (observed: ~2e-6 on both backends).
ROLLOUT_F32_RTOL = 5e-5


def rollout_value_and_grads(particles: Particles, policy, start: Gaussian, horizon: int) -> tuple[Tensor, ...]:
    """V and ∂V/∂ψ for every policy parameter (float64)."""
    value = particles.rollout(start, horizon).value
    return value.detach(), *torch.autograd.grad(value, tuple(policy.parameters()))


def old_matheron_paths(draw: FeatureDraw, cache: GPPosteriorCache) -> MatheronPaths:
    """Matheron's rule as first written, all in float64: the bits ``dtype=float64`` must keep."""
    theta = cache.hyperparameters
    data, _, _ = scaled(cache)
    frequencies, phases, weights, update_noise = (t.to(DTYPE) for t in draw)  # drawn in float32 (DRAW_DTYPE)
    weights = (2.0 * theta.signal_variance / frequencies.shape[-2]).sqrt()[..., None, None] * weights
    prior_at_data = torch.cos(data @ frequencies.mT + phases[..., None, :]) @ weights.mT
    residual = prior_at_data + theta.noise_variance.sqrt()[..., None, None] * update_noise
    update = cache.beta[..., :, None] - cache.K_inv @ residual
    return MatheronPaths(frequencies, phases, weights, update.mT.contiguous())


def matheron_in(cache: GPPosteriorCache, draw: FeatureDraw, dtype: torch.dtype | None) -> MatheronPaths:
    """:func:`matheron_paths` of ``cache``'s GP for ``draw``, the functions in ``dtype``."""
    theta = cache.hyperparameters
    data, _, _ = scaled(cache)
    return matheron_paths(draw, data, cache.beta, cache.K_inv, theta.signal_variance, theta.noise_variance,
                          dtype=dtype)


# The float32 prior sample at the data f̃_p(X) (cos and the `n x L` by `L x P` product in float32) against the
# float64 one, through the float64 solve, on a drawn function's values, relative to the largest |f|: each entry
# of f̃_p(X) carries ~√L float32 ulp (2⁻²⁴ ≈ 6e-8) of Σ_l |W_pl| ≲ α √(2L), and f moves by k(x, X) K⁻¹ of that,
# the GP's smoothing of it (observed ~6e-7 here; ~4e-4 with v in float32 on the 250-point cart-pole data, where
# rounding v alone to float32 moves f as much).
PRIOR_F32_RTOL = 2e-5


@pytest.mark.parametrize("num_features", [64, 257])
def test_matheron_paths_float32_prior_at_data_equals_float64(gp_factory, num_features):
    gp = gp_factory(40, 3, 1, (1,), seed=22)
    cache = gp.posterior_cache()
    data, data_sq, _ = scaled(cache)
    num_outputs, num_points, input_dim = data.shape
    draw = draw_features(torch.Generator().manual_seed(4), num_outputs, input_dim, num_points, 33, num_features)
    double, single = matheron_in(cache, draw, None), matheron_in(cache, draw, torch.float32)
    # float64 (the default, or asked for): the original bits.
    for paths in (double, matheron_in(cache, draw, DTYPE)):
        for got, want in zip(paths, old_matheron_paths(draw, cache), strict=True):
            assert got.dtype == DTYPE and torch.equal(got, want)
    assert double.update.is_contiguous() and single.update.is_contiguous()
    # float32: ω̃, b and W are the float64 ones rounded; v differs by the float32 prior at the data.
    for got, want in zip(single[:3], double[:3], strict=True):
        assert got.dtype == torch.float32 and torch.equal(got, want.float())
    assert single.update.dtype == torch.float32 and not torch.equal(single.update, double.update.float())
    # The functions' values, both evaluated in float64 (the float32 update cast up): only v differs.
    z = torch.randn(num_outputs, 33, input_dim, generator=torch.Generator().manual_seed(5), dtype=DTYPE)
    z = torch.stack([z, data[:, :33]])  # random points, and points at the data (where v matters most)
    signal_variance = cache.hyperparameters.signal_variance
    want = path_values(z, data, data_sq, signal_variance, double)
    got = path_values(z, data, data_sq, signal_variance, MatheronPaths(*double[:3], single.update.double()))
    assert 0 < (got - want).abs().max() <= PRIOR_F32_RTOL * want.abs().max()


def test_path_dtype_float32_keeps_the_float64_functions_in_float32(gp_factory):
    # ω̃, b, W are the float64 draw's rounded to float32; v is solved in float64 and cast (its prior at the
    # data formed in float32: see the test above); float64 functions keep the original bits.
    gp, policy, reward = pendulum_parts(gp_factory)
    double, single = pathwise(gp, policy, reward), pathwise(gp, policy, reward, path_dtype="float32")
    for got, want in zip(double.functions(), old_matheron_paths(draw_of(double), gp.posterior_cache()), strict=True):
        assert torch.equal(got, want)
    for d, s in zip(double.functions()[:3], single.functions()[:3], strict=True):
        assert d.dtype == DTYPE and s.dtype == torch.float32
        assert torch.equal(s, d.float())
    update = single.functions().update
    assert update.dtype == torch.float32
    assert torch.equal(update, matheron_in(gp.posterior_cache(), draw_of(double), torch.float32).update)


def draw_of(particles: Particles, draw: int = 0) -> FeatureDraw:
    """The standard random numbers of pathwise draw ``draw``, as :meth:`Particles.functions` draws them."""
    gen = torch.Generator().manual_seed(_draw_seed(particles.seed, draw, PATHWISE_STREAM))
    num_outputs, num_points, input_dim = particles._data.shape[-3:]
    return draw_features(gen, num_outputs, input_dim, num_points, particles.num_particles, particles.num_features)


@pytest.mark.parametrize("name", ["native", "torch"])
def test_path_dtype_float32_values_and_gradients_equal_float64(gp_factory, name):
    gp, policy, reward = pendulum_parts(gp_factory)
    double, single = pathwise(gp, policy, reward), pathwise(gp, policy, reward, path_dtype="float32")
    gen = torch.Generator().manual_seed(8)
    z = (torch.randn(3, 16, 5, generator=gen, dtype=DTYPE) * double._inv_lengthscales).requires_grad_()
    probe = torch.randn(3, 16, generator=gen, dtype=DTYPE)
    results = []
    engine = Engine.resolve(name, "reference")
    for particles in (double, single):
        value = path_values(z.to(particles._eval_dtype), particles._path_data, particles._path_data_sq,
                            particles._path_signal_variance, particles.functions(), engine).to(DTYPE)
        results.append((value, *torch.autograd.grad((value * probe).sum(), z)))
    assert results[1][0].dtype == DTYPE
    for got, want in zip(results[1], results[0], strict=True):
        scale = want.abs().max()
        assert 0 < (got - want).abs().max() <= PATH_F32_RTOL * scale  # > 0: float32 really ran


@pytest.mark.parametrize("name", ["native", "torch"])
def test_path_dtype_float32_rollout_equals_float64(gp_factory, name):
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.tensor([0.1, 2.5, -0.3], dtype=DTYPE), torch.diag(torch.tensor([0.04, 0.2, 0.09],
                                                                                         dtype=DTYPE)))
    engine = Engine.resolve(name, "reference")
    want = rollout_value_and_grads(pathwise(gp, policy, reward, engine=engine), policy, start, 5)
    got = rollout_value_and_grads(pathwise(gp, policy, reward, path_dtype="float32", engine=engine), policy, start, 5)
    assert got[0].dtype == DTYPE
    for g, w in zip(got, want, strict=True):
        assert 0 < (g - w).abs().max() <= ROLLOUT_F32_RTOL * w.abs().max()


def test_path_dtype_float64_is_the_default_bit_for_bit(gp_factory):
    # The default evaluates in the propagation's dtype with no cast: explicit float64 gives the same bits,
    # and the first step from a point start is x_0 + f_p(z̃_0) of the float64 path values, exactly.
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.tensor([0.1, 2.5, -0.3], dtype=DTYPE), 0.05 * torch.eye(3, dtype=DTYPE))
    default = pathwise(gp, policy, reward)
    explicit = pathwise(gp, policy, reward, path_dtype="float64")
    assert default.path_dtype == "float64"
    for got, want in zip(rollout_value_and_grads(explicit, policy, start, 5),
                         rollout_value_and_grads(default, policy, start, 5), strict=True):
        assert torch.equal(got, want)
    point = Gaussian(torch.tensor([0.1, 0.2, -0.3], dtype=DTYPE), torch.zeros(3, 3, dtype=DTYPE))
    particles = pathwise(gp, policy, reward, include_noise=False)
    with torch.no_grad():
        states, actions = particles.trajectories(point, 1)
        data, data_sq, inv_ls = scaled(gp.posterior_cache())
        z = torch.cat([AngleFeatures(3, (1,))(states[:, 0]), actions[:, 0]], dim=-1)[None] * inv_ls
        f = path_values(z, data, data_sq, gp.posterior_cache().hyperparameters.signal_variance,
                        particles.functions())
    assert f.dtype == DTYPE and torch.equal(states[:, 1], states[:, 0] + f.mT)


def test_bad_path_dtype_is_a_user_error(gp_factory):
    gp, policy, reward = pendulum_parts(gp_factory)
    with pytest.raises(UserError, match=r"propagation\.path_dtype must be one of float64, float32, got 'float16'"):
        pathwise(gp, policy, reward, path_dtype="float16")
    with pytest.raises(UserError, match=r"propagation\.path_dtype must be one of"):
        build(tiny_config("propagation=particles", "propagation.path_dtype=float16"))
    parts = build(tiny_config("propagation=particles", "propagation.path_dtype=float32"))
    assert factory_keywords(parts.make_propagator)["path_dtype"] == "float32"


def test_functions_of_a_gp_with_per_tuple_noise_converge_to_its_posterior(gp_factory, mc):
    # Source samples of relevance w have noise σ_ε² + c (qtl.models.point_noise): ε_p ~ N(0, σ_ε²I + C) in the update,
    # so over draws the functions' moments are that GP's posterior (its K_inv is (K + σ_ε²I + C)⁻¹).
    gp = gp_factory(30, 2, 1, seed=12)
    extra = torch.linspace(0.0, 0.05, 30, dtype=DTYPE)[:, None].expand(-1, 2)
    weighted = DynamicsGP(gp.train_x, gp.train_y, gp.hyperparameters, extra_noise=extra)
    cache = weighted.posterior_cache()
    theta = cache.hyperparameters
    data, _, _ = scaled(cache)
    draws = [draw_features(torch.Generator().manual_seed(seed), 2, data.shape[-1], 30, 200, 64) for seed in range(300)]
    draw = FeatureDraw(*(torch.stack(parts) for parts in zip(*draws, strict=True)))
    paths = matheron_paths(draw, data, cache.beta, cache.K_inv, theta.signal_variance, theta.noise_variance,
                           extra_noise=cache.extra_noise)
    points = torch.tensor([[0.1, -0.2, 0.3], [0.5, 0.4, -0.6], [-1.0, 0.8, 0.0]], dtype=DTYPE)
    mean, cov = exact_posterior(cache, points)
    values = values_at(cache, paths, points)
    mc.assert_mean(mean, values.mean(1), "mean over draws")
    mc.assert_mean(cov, centred_products(values, mean).mean(1), "covariance over draws")
    # Without the extra noise in ε_p the spread is wrong where c is large: the check above can fail.
    plain = matheron_paths(draw, data, cache.beta, cache.K_inv, theta.signal_variance, theta.noise_variance)
    assert not torch.allclose(values_at(cache, plain, points).var(1).mean(0), values.var(1).mean(0), rtol=1e-3)
