"""The native pathwise-function values (`pathwise.c`) against the torch `_PathValues`: values, ∂f/∂z, rollouts."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from torch import Tensor

from qtl.gaussian import Gaussian
from qtl.kernels.engine import Engine
from qtl.kernels.native import pathwise as native_pathwise
from qtl.kernels.native.pathwise import NativePathValues, check_against_torch, load_path_values
from qtl.policies import RBFPolicy, SquashedPolicy
from qtl.propagation import Particles
from qtl.propagation.pathwise import MatheronPaths, _PathValues, path_values
from tests.helpers import quadratic_reward

DTYPE = torch.float64
RTOL = 1e-12
ROLLOUT_RTOL = 1e-10


@pytest.fixture(scope="module")
def library(built):
    """The compiled library (built once for the module)."""
    return load_path_values()


def make_problem(
    point_batch: tuple[int, ...], model_batch: tuple[int, ...], num_out: int, num_paths: int, num: int,
    num_features: int, dim: int, seed: int, dtype: torch.dtype = DTYPE,
) -> tuple[Tensor, Tensor, Tensor, Tensor, MatheronPaths]:  # fmt: skip
    """Points z `*point_batch x E x P x D` and the model's data, |data|², α² and paths with `model_batch`."""
    gen = torch.Generator().manual_seed(seed)
    like = {"generator": gen, "dtype": dtype}
    z = 0.8 * torch.randn(*point_batch, num_out, num_paths, dim, **like)
    data = torch.randn(*model_batch, num_out, num, dim, **like)
    signal_variance = 0.5 + torch.rand(*model_batch, num_out, **like)
    paths = MatheronPaths(
        frequencies=torch.randn(num_out, num_features, dim, **like),
        phases=2 * math.pi * torch.rand(num_out, num_features, **like),
        weights=torch.randn(*model_batch, num_out, num_paths, num_features, **like) / num_features**0.5,
        update=torch.randn(*model_batch, num_out, num_paths, num, **like),
    )
    return z, data, data.square().sum(-1), signal_variance, paths


def probe_for(value: Tensor, probe_seed: int = 7) -> Tensor:
    """A random probe of ``value``'s shape and dtype (the same numbers in any dtype)."""
    return torch.randn(value.shape, generator=torch.Generator().manual_seed(probe_seed), dtype=DTYPE).to(value.dtype)


def values_and_grad(fn, z: Tensor, probe_seed: int = 7) -> tuple[Tensor, Tensor]:
    """f = fn(z) and the gradient of Σ probe · f for ``z`` (:func:`probe_for`)."""
    z = z.detach().clone().requires_grad_()
    value = fn(z)
    probe = probe_for(value, probe_seed)
    (grad,) = torch.autograd.grad((value * probe).sum(), z)
    return value, grad


def assert_rel_close(got: Tensor, want: Tensor, rtol: float) -> None:
    """Same shape, and every entry within ``rtol`` of the largest reference magnitude."""
    assert got.shape == want.shape
    err, scale = (got - want).abs().max().item(), want.abs().max().item()
    assert scale > 0 and err <= rtol * scale, f"max error {err:.3g} vs scale {scale:.3g}"


# (point batch, model batch, E, P, n, L, D): odd n, n = 1, L = 1, P = 1, restarts over a shared model,
# restarts against stacked models, a model batch wider than the points', and plain single items.
SHAPES = [
    ((), (), 3, 5, 7, 9, 4),
    ((), (), 2, 4, 1, 6, 3),
    ((), (), 2, 4, 6, 1, 3),
    ((), (), 2, 1, 5, 5, 2),
    ((), (), 1, 3, 1, 1, 1),
    ((3,), (), 4, 40, 37, 33, 6),
    ((2, 3), (3,), 2, 9, 11, 17, 5),
    ((2, 1), (1, 3), 2, 6, 5, 8, 3),
    ((), (3,), 2, 5, 13, 10, 4),
    ((2,), (3, 1), 3, 4, 9, 7, 2),
]


@pytest.mark.parametrize(("point_batch", "model_batch", "num_out", "num_paths", "num", "num_features", "dim"), SHAPES)
def test_native_equals_torch_values_and_gradients(
    library, point_batch, model_batch, num_out, num_paths, num, num_features, dim
):
    z, data, data_sq, signal_variance, paths = make_problem(
        point_batch, model_batch, num_out, num_paths, num, num_features, dim, seed=len(point_batch) + num
    )
    native = values_and_grad(
        lambda z: native_pathwise.path_values(z, data, signal_variance, *paths, library=library), z
    )
    reference = values_and_grad(lambda z: _PathValues.apply(z, data, data_sq, signal_variance, paths), z)
    for got, want in zip(native, reference, strict=True):
        assert_rel_close(got, want, RTOL)


def test_broadcast_and_strided_operands_are_read_in_place(library):
    # z broadcast over the particles (one point, stride 0, as tests/propagation does) and non-contiguous
    # model operands (a transposed view of the update, frequencies of a stacked draw): the same numbers.
    _, data, data_sq, signal_variance, paths = make_problem((2,), (), 3, 6, 11, 7, 4, seed=3)
    z = torch.randn(2, 3, 1, 4, generator=torch.Generator().manual_seed(4), dtype=DTYPE).expand(-1, -1, 6, -1)
    update_t = paths.update.mT.contiguous().mT  # `E x P x n`, unit stride along P
    frequencies = torch.stack([paths.frequencies, paths.frequencies])  # `2 x E x L x D`: one per z batch item
    strided = MatheronPaths(frequencies, paths.phases, paths.weights, update_t)
    native = values_and_grad(
        lambda z: native_pathwise.path_values(z, data, signal_variance, *strided, library=library), z
    )
    reference = values_and_grad(lambda z: _PathValues.apply(z, data, data_sq, signal_variance, paths), z)
    for got, want in zip(native, reference, strict=True):
        assert_rel_close(got, want, RTOL)


def test_thread_counts_give_identical_results(library):
    z, data, _, signal_variance, paths = make_problem((3,), (), 2, 70, 19, 23, 3, seed=5)
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            results.append(
                values_and_grad(
                    lambda z: native_pathwise.path_values(z, data, signal_variance, *paths, library=library), z
                )
            )
    finally:
        torch.set_num_threads(before)
    for got, want in zip(*results, strict=True):
        assert torch.equal(got, want)


def test_gradcheck_native_function(library):
    z, data, _, signal_variance, paths = make_problem((2,), (), 2, 3, 5, 4, 3, seed=6)
    z = z.requires_grad_()
    assert torch.autograd.gradcheck(
        lambda z: NativePathValues.apply(z, data, signal_variance, *paths, library, True), (z,)
    )


def test_no_gradient_is_formed_without_grad_mode(library, monkeypatch):
    z, data, _, signal_variance, paths = make_problem((), (), 2, 3, 5, 4, 3, seed=8)
    asked = []
    values = library.values
    monkeypatch.setattr(library, "values", lambda *args: asked.append(args[-1]) or values(*args))
    with torch.no_grad():
        native_pathwise.path_values(z.requires_grad_(), data, signal_variance, *paths, library=library)
    native_pathwise.path_values(z, data, signal_variance, *paths, library=library)
    assert asked == [False, True]


def test_path_values_dispatch_native_for_float64_and_float32(library, monkeypatch):
    # Operands all float64 or all float32 take the kernel of their precision; mixed dtypes take torch.
    calls = []
    apply = NativePathValues.apply
    monkeypatch.setattr(NativePathValues, "apply", lambda *args: calls.append(args[0].dtype) or apply(*args))
    for dtype in (torch.float32, DTYPE):
        z, data, data_sq, signal_variance, paths = make_problem((2,), (), 2, 5, 6, 7, 3, seed=9, dtype=dtype)
        operands = (data, data_sq, signal_variance, paths)
        got = values_and_grad(lambda z, operands=operands: path_values(z, *operands, Engine(exp_sums="native")), z)
        want = values_and_grad(lambda z, operands=operands: path_values(z, *operands, Engine()), z)
        for g, w in zip(got, want, strict=True):
            assert g.dtype == dtype
            assert_rel_close(g, w, F32_RTOL if dtype == torch.float32 else RTOL)
    assert calls == [torch.float32, DTYPE]
    assert not native_pathwise.native_fits(z.float(), data, signal_variance)  # mixed dtypes: not the kernel


def term_scales(z: Tensor, data: Tensor, signal_variance: Tensor, paths: MatheronPaths) -> tuple[Tensor, Tensor]:
    """Σ of the terms' magnitudes of f `... x E x P` and of ∂f/∂z̃ `... x E x P x 1` (float64, from float64 operands).

    f = Σ_l W_pl cos(a_l) + Σ_i k_i v_pi: its float32 round-off is relative to Σ_l |W_pl| + Σ_i |k_i v_pi|
    (the terms may cancel), and that of ∂f/∂z̃, formed (natively and by the torch twin) as
    Σ_i k_i v_pi x̃_i − z̃ Σ_i k_i v_pi − Σ_l W_pl sin(a_l) ω̃_l, to Σ_i |k_i v_pi| (|x̃_i| + |z̃|) + Σ_l |W_pl| |ω̃_l|.
    """
    diff = z[..., :, None, :] - data[..., None, :, :]  # ... x E x P x n x D
    kv = (signal_variance[..., None, None] * torch.exp(-0.5 * diff.square().sum(-1)) * paths.update).abs()
    weights = paths.weights.abs()
    value = kv.sum(-1) + weights.sum(-1)
    spread = data.norm(dim=-1)[..., None, :] + z.norm(dim=-1)[..., None]  # |x̃_i| + |z̃|: ... x E x P x n
    grad = (kv * spread).sum(-1) + (weights * paths.frequencies.norm(dim=-1)[..., None, :]).sum(-1)
    return value, grad[..., None]


def assert_within_scale(got: Tensor, want: Tensor, scale: Tensor, rtol: float) -> None:
    """Same shape, every entry within ``rtol`` times its row's term scale (``scale`` broadcasts against it)."""
    assert got.shape == want.shape
    ratio = ((got.double() - want.double()).abs() / scale).max().item()
    assert ratio <= rtol, f"max error {ratio:.3g} of the term scale"


# float32 against float64, relative to the sum of the terms' magnitudes (term_scales). Each term is
# formed from float32 operands (relative round-off u = 2⁻²⁴ ≈ 6e-8 each) in a few operations: the
# angle a_l = ω̃ᵀz̃ + b to within ~(D + 2) u |a| absolutely, so cos(a_l) and sin(a_l) to within
# ~(D + 2)(1 + |a|) u ≈ 2e-6 for D ≤ 6, |a| ≲ 3 (z̃ ~ 0.8 N(0, 1), ω̃ ~ N(0, I) here); k_i through its
# exponent −½|z̃ − x̃|² (the torch twin's |z̃|² + |x̃|² − 2z̃ᵀx̃ to ~u(|z̃|² + |x̃|²)) likewise; libmvec adds
# ≤ 4 ulp; the sums add ≲ (L/PAD + 4 lanes) u ≈ 1e-6 of the scale (blocked accumulators). So a few
# 1e-6 of the term scale (≤ 5e-6 observed on SHAPES); F32_RTOL = 1e-5.
F32_RTOL = 1e-5


@pytest.mark.parametrize(("point_batch", "model_batch", "num_out", "num_paths", "num", "num_features", "dim"), SHAPES)
def test_float32_values_and_gradients_equal_float64_to_the_round_off_of_the_terms(
    library, point_batch, model_batch, num_out, num_paths, num, num_features, dim
):
    # The float32 kernel and the float32 torch twin against float64, and against each other.
    z, data, data_sq, signal_variance, paths = make_problem(
        point_batch, model_batch, num_out, num_paths, num, num_features, dim, seed=len(point_batch) + num
    )
    single = (data.float(), signal_variance.float(), MatheronPaths(*(t.float() for t in paths)))
    truth = values_and_grad(lambda z: _PathValues.apply(z, data, data_sq, signal_variance, paths), z)
    native = values_and_grad(
        lambda z: native_pathwise.path_values(z, single[0], single[1], *single[2], library=library), z.float()
    )
    torch32 = values_and_grad(
        lambda z: _PathValues.apply(z, single[0], data_sq.float(), single[1], single[2]), z.float()
    )
    value_scale, grad_scale = term_scales(z, data, signal_variance, paths)
    # The gradient is of Σ probe · f, summed over the model items that z broadcasts against.
    grad_scale = (grad_scale * probe_for(truth[0]).abs()[..., None]).sum_to_size(*z.shape[:-1], 1)
    scales = (value_scale, grad_scale)
    for got32, want32, want, scale in zip(native, torch32, truth, scales, strict=True):
        assert got32.dtype == torch.float32 and want32.dtype == torch.float32
        assert_within_scale(got32, want, scale, F32_RTOL)
        assert_within_scale(want32, want, scale, F32_RTOL)
        assert_within_scale(got32, want32, scale, F32_RTOL)
    assert not torch.equal(native[0].double(), truth[0])  # float32 really ran


def test_float32_thread_counts_give_identical_results(library):
    z, data, _, signal_variance, paths = make_problem((3,), (), 2, 70, 19, 23, 3, seed=5, dtype=torch.float32)
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            results.append(values_and_grad(
                lambda z: native_pathwise.path_values(z, data, signal_variance, *paths, library=library), z
            ))
    finally:
        torch.set_num_threads(before)
    for got, want in zip(*results, strict=True):
        assert torch.equal(got, want)


def test_build_check_passes_and_catches_a_wrong_kernel(library):
    check_against_torch(library)

    class Broken:
        def values(self, *args):
            value, grad = library.values(*args)
            return value * (1 + 1e-9), grad

    with pytest.raises(RuntimeError, match="disagrees"):
        check_against_torch(Broken())  # type: ignore[arg-type]


def rollout_value_and_grads(particles: Particles, policy: torch.nn.Module, start: Gaussian, horizon: int):
    """V (per batch item) and ∂(Σ V)/∂ψ for every policy parameter."""
    value = particles.rollout(start, horizon).value
    return value.detach(), torch.autograd.grad(value.sum(), tuple(policy.parameters()))


@pytest.mark.parametrize("stacked", [False, True])
def test_particle_rollout_equal_between_backends(library, gp_factory, monkeypatch, stacked):
    # A whole pathwise rollout (angles, squashed RBF policy, noise) on the native and the torch path:
    # the same V and ∂V/∂ψ. Stacked: 2 restarts x 2 stacked models broadcast against each other.
    gps = [gp_factory(40, 3, 1, (1,), seed=s) for s in (22, 23)]
    gen = torch.Generator().manual_seed(23)
    policy = SquashedPolicy(
        RBFPolicy(4, 1, 8, targets=torch.randn(8, 1, generator=gen, dtype=DTYPE), generator=gen), 2.0
    )
    model = [g.posterior_cache() for g in gps] if stacked else gps[0]
    def particles(engine: Engine) -> Particles:
        return Particles(model, policy, quadratic_reward(3, (1,)), angle_dims=(1,), sampling="pathwise",
                         num_particles=24, num_features=50, seed=3, engine=engine)

    mean = torch.tensor([0.1, 2.5, -0.3], dtype=DTYPE)
    if stacked:
        mean = mean + 0.2 * torch.randn(2, 1, 3, generator=gen, dtype=DTYPE)
    start = Gaussian(mean, 0.05 * torch.eye(3, dtype=DTYPE).expand(*mean.shape[:-1], 3, 3))
    calls = []
    apply = NativePathValues.apply
    monkeypatch.setattr(NativePathValues, "apply", lambda *args: calls.append(1) or apply(*args))
    results = {}
    for name in ("native", "torch"):
        results[name] = rollout_value_and_grads(particles(Engine(exp_sums=name)), policy, start, 6)
    assert len(calls) == 6  # the native backend took the kernel at every step, the torch backend never
    (v_native, g_native), (v_torch, g_torch) = results["native"], results["torch"]
    assert v_native.shape == ((2, 2) if stacked else ())
    assert_rel_close(v_native, v_torch, ROLLOUT_RTOL)
    for got, want in itertools.zip_longest(g_native, g_torch):
        assert_rel_close(got, want, ROLLOUT_RTOL)


@pytest.mark.parametrize("reach", [1.0, 30.0, 300.0, 3000.0])
def test_float32_sin_and_cos_hold_for_large_angles(library, reach):
    # With ∂f/∂z̃ the float32 kernel takes sin and cos from one argument reduction (pathwise.c, sincos_f32):
    # against float64 it is as good as float32 allows, whose angle a = ω̃ᵀz̃ + b itself carries ≤ (D + 2) u |a|
    # (u = 2⁻²⁴) per term, also for |a| in the thousands (observed: ~2e-9 |a| of the term scale, the terms'
    # errors partly cancelling). Data far away (k ≈ 0): f and ∂f/∂z̃ are the random-feature part alone.
    z, data, _, signal_variance, paths = make_problem((), (), 2, 64, 5, 200, 3, seed=11)
    z = z * reach
    data = data + 1e3
    single = (data.float(), signal_variance.float(), MatheronPaths(*(t.float() for t in paths)))
    truth = values_and_grad(lambda z: native_pathwise.path_values(z, data, signal_variance, *paths, library=library), z)
    got = values_and_grad(
        lambda z: native_pathwise.path_values(z, single[0], single[1], *single[2], library=library), z.float()
    )
    angle = (z @ paths.frequencies.mT + paths.phases[..., None, :]).abs().amax()  # the largest |a|
    assert angle > 0.5 * reach
    value_scale, grad_scale = term_scales(z, data, signal_variance, paths)
    grad_scale = grad_scale * probe_for(truth[0]).abs()[..., None]
    for g, w, scale in zip(got, truth, (value_scale, grad_scale), strict=True):
        assert_within_scale(g, w, scale * (1 + angle), (3 + 2) * 2.0**-24)
