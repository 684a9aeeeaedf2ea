"""The fused exp sum Σ_ij W_ij exp((A Bᵀ)_ij): the torch path, its native twin, and the switch between them."""

from __future__ import annotations

import itertools
import logging
from pathlib import Path

import pytest
import torch
from torch import Tensor

from qtl.errors import UserError
from qtl.gaussian import Gaussian
from qtl.kernels import SEKernelMoments, weighted_exp_sum
from qtl.kernels import engine as engine_module
from qtl.kernels.engine import Engine
from qtl.kernels.native import exp_sum as native_exp_sum
from qtl.kernels.native import loader

DTYPE = torch.float64
RTOL = 1e-12  # native vs torch, relative, float64

# (batch of A, batch of B, batch of W, n, m, K): odd n, n below a tile, n != m, n and m across the
# kernel's row split (256) and column chunk (128), n not a multiple of its row block (8 with AVX-512)
# and m not one of its vector width (8), K below, at and above that width, broadcast A or W (W
# `P x n x m` under `R x P`).
SHAPES = [
    ((), (), (), 1, 1, 1),
    ((3,), (3,), (3,), 7, 5, 2),
    ((2, 10), (2, 10), (10,), 33, 33, 8),
    ((4,), (4,), (4,), 257, 257, 8),
    ((1, 3), (2, 3), (3,), 300, 513, 9),
    ((2, 1), (2, 3), (1, 3), 5, 600, 4),
]
SMALL = ((2, 3), (2, 3), (3,), 5, 6)  # batches of A, B, W and n, m for the K sweep
# Which of A, B, W need a gradient: every non-empty combination. Without W the native forward also
# forms the A/B gradients (G_A, G_B); with W its backward recomputes exp(A Bᵀ).
WANTS = [want for want in itertools.product((True, False), repeat=3) if any(want)]


NATIVE = Engine(exp_sums="native")


@pytest.fixture
def native(built: Path) -> Engine:
    """The native exp sums (the library built)."""
    return NATIVE


def native_sum(a: Tensor, b: Tensor, w: Tensor) -> Tensor:
    """:func:`weighted_exp_sum` by the native kernel."""
    return weighted_exp_sum(a, b, w, engine=NATIVE)


def operands(shape: tuple, seed: int, requires_grad: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """Random A, B (entries ~ N(0, 0.3²)) and a signed W of the given batch shapes and sizes."""
    batch_a, batch_b, batch_w, n, m, k = shape
    gen = torch.Generator().manual_seed(seed)
    a = 0.3 * torch.randn(*batch_a, n, k, generator=gen, dtype=DTYPE)
    b = 0.3 * torch.randn(*batch_b, m, k, generator=gen, dtype=DTYPE)
    w = torch.randn(*batch_w, n, m, generator=gen, dtype=DTYPE)
    return tuple(t.requires_grad_(requires_grad) for t in (a, b, w))


def with_grads(a: Tensor, b: Tensor, w: Tensor, name: str) -> tuple[Tensor, ...]:
    """The sums under backend ``name`` and the gradients of a weighted total w.r.t. those of A, B, W that need one."""
    value = weighted_exp_sum(a, b, w, engine=Engine(exp_sums=name))
    probe = torch.linspace(0.5, 1.5, value.numel(), dtype=DTYPE).view(value.shape)
    wanted = tuple(t for t in (a, b, w) if t.requires_grad)
    return (value.detach(), *torch.autograd.grad((value * probe).sum(), wanted))


def needing(want: tuple[bool, bool, bool], *tensors: Tensor) -> tuple[Tensor, ...]:
    """Detached copies of ``tensors`` of which those flagged in ``want`` need a gradient."""
    return tuple(t.detach().requires_grad_(flag) for t, flag in zip(tensors, want, strict=True))


def assert_relative(got: Tensor, want: Tensor, scale: Tensor, what: str) -> None:
    """|got − want| <= RTOL · scale entrywise (scale: the magnitude the result is a sum of)."""
    assert got.shape == want.shape, what
    err = ((got - want).abs() / scale).max().item()
    assert err <= RTOL, f"{what}: relative error {err:.2e} > {RTOL:.0e}"


def test_torch_path_value_and_gradcheck():
    gen = torch.Generator().manual_seed(0)
    a = (0.3 * torch.randn(2, 3, 5, 4, generator=gen, dtype=DTYPE)).requires_grad_()
    b = (0.3 * torch.randn(2, 3, 6, 4, generator=gen, dtype=DTYPE)).requires_grad_()
    w = torch.randn(3, 5, 6, generator=gen, dtype=DTYPE).requires_grad_()  # broadcast over dim 0
    expected = (w * torch.exp(a @ b.mT)).sum((-2, -1))
    # The torch path (the default engine): whole matrix at once, and in blocks of 2 rows (the last block partial).
    for rows in (5, 2):
        torch.testing.assert_close(weighted_exp_sum(a, b, w, block_rows=rows), expected)
        assert torch.autograd.gradcheck(lambda *t, r=rows: weighted_exp_sum(*t, block_rows=r), (a, b, w))
    # A with a broadcast batch dimension; W with the full batch shape.
    a1 = a[:1].detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda *t: weighted_exp_sum(*t, block_rows=2), (a1, b, w))
    w_full = w.detach().expand(2, -1, -1, -1).clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda *t: weighted_exp_sum(*t, block_rows=2), (a, b, w_full))


@pytest.mark.parametrize(("shape", "seed"), [(s, i) for i, s in enumerate(SHAPES)])
@pytest.mark.parametrize("want", WANTS, ids=lambda want: "".join(n for n, f in zip("abw", want, strict=True) if f))
def test_native_equals_torch(built, shape, seed, want):
    a, b, w = needing(want, *operands(shape, seed))
    native = with_grads(a, b, w, "native")
    reference = with_grads(a, b, w, "torch")
    # Scales: the same sums and gradients with |W|, so that cancellation in a signed W is not
    # mistaken for an error (the 1e-12 is relative to what the result is a sum of).
    a_all, b_all, w_all = needing((True, True, True), a, b, w)
    full = with_grads(a_all, b_all, w_all, "torch")
    scale = with_grads(a_all, b_all, w_all.detach().abs().requires_grad_(), "torch")
    scales = (scale[0], scale[1].abs().amax(), scale[2].abs().amax(), full[3].abs().amax())
    kept = [(mag, what) for mag, what, flag in zip(scales[1:], "ABW", want, strict=True) if flag]
    assert len(native) == len(reference) == 1 + len(kept)
    for got, want_, (mag, what) in zip(native, reference, [(scales[0], "value"), *kept], strict=True):
        assert_relative(got, want_, mag, f"{shape} {what}")


@pytest.mark.parametrize("k", [*range(1, 10), 16, 17])  # K > 8: one pass of the A/B gradients per 8 k's
def test_native_equals_torch_for_every_k(built, k):
    a, b, w = operands((*SMALL, k), k, requires_grad=True)
    w = w.detach().abs().requires_grad_()  # positive weights: entrywise relative errors
    for got, want in zip(with_grads(a, b, w, "native"), with_grads(a, b, w, "torch"), strict=True):
        assert_relative(got, want, want.abs(), f"K={k}")


def test_native_gradcheck(native):
    for shape in [((2, 3), (2, 3), (3,), 5, 6, 4), ((1,), (2,), (), 3, 4, 2), ((), (), (), 259, 3, 1)]:
        a, b, w = operands(shape, 3, requires_grad=True)
        assert torch.autograd.gradcheck(native_sum, (a, b, w)), shape
    # Only some operands need gradients. W fixed (the GP dynamics): the forward forms G_A and G_B,
    # across the row split (n = 259: two partial G_B added) and the column chunk (m = 513).
    fixed_w = [
        ((2, 3), (2, 3), (3,), 5, 6, 4),
        ((1,), (2,), (), 3, 4, 2),
        ((), (), (), 259, 3, 1),
        ((), (), (), 3, 513, 1),
    ]
    for shape, want in itertools.product(fixed_w, [(True, True, False), (True, False, False), (False, True, False)]):
        a, b, w = needing(want, *operands(shape, 4))
        assert torch.autograd.gradcheck(native_sum, (a, b, w)), (shape, want)
    # W needs one and A or B not (backward recomputes exp(A Bᵀ)).
    for want in [(False, False, True), (True, False, True), (False, True, True)]:
        a, b, w = needing(want, *operands(((2, 3), (2, 3), (3,), 5, 6, 4), 5))
        assert torch.autograd.gradcheck(native_sum, (a, b, w)), want


def test_native_forward_forms_the_a_b_gradients_only_when_w_is_fixed(native, monkeypatch):
    calls: list[tuple[str, tuple[bool, ...]]] = []
    forward, backward = native_exp_sum.ExpSumLibrary.forward, native_exp_sum.ExpSumLibrary.backward

    def spy_forward(self, a, b, w, offsets, with_grads=(False, False)):
        calls.append(("forward", tuple(with_grads)))
        return forward(self, a, b, w, offsets, with_grads)

    def spy_backward(self, a, b, w, offsets, grad, needs):
        calls.append(("backward", tuple(needs)))
        return backward(self, a, b, w, offsets, grad, needs)

    monkeypatch.setattr(native_exp_sum.ExpSumLibrary, "forward", spy_forward)
    monkeypatch.setattr(native_exp_sum.ExpSumLibrary, "backward", spy_backward)
    base = operands(SHAPES[4], 10)
    expected = {
        (True, True, False): [("forward", (True, True))],
        (True, False, False): [("forward", (True, False))],
        (False, True, False): [("forward", (False, True))],
        (True, True, True): [("forward", (False, False)), ("backward", (True, True, True))],
        (False, False, True): [("forward", (False, False)), ("backward", (False, False, True))],
    }
    for want, seen in expected.items():
        calls.clear()
        tensors = needing(want, *base)
        torch.autograd.grad(native_sum(*tensors).sum(), [t for t in tensors if t.requires_grad])
        assert calls == seen, want
    # No gradient wanted, or grad mode off: the plain sums, the same bits as with G_A, G_B.
    calls.clear()
    fused = native_sum(*needing((True, True, False), *base))
    with torch.no_grad():
        off = native_sum(*needing((True, True, False), *base))
    plain = native_sum(*base)
    assert calls == [("forward", (True, True)), ("forward", (False, False)), ("forward", (False, False))]
    assert torch.equal(fused.detach(), off) and torch.equal(off, plain)


@pytest.mark.parametrize("w_grad", [True, False], ids=["recompute", "fused"])
def test_native_is_bit_identical_across_calls_and_thread_counts(native, w_grad):
    # n = 600: three row splits, so G_B or dL/dB is a sum of three per-unit partials (fixed order).
    a, b, w = needing((True, True, w_grad), *operands(((2, 10), (2, 10), (10,), 600, 300, 8), 5))
    wanted = [t for t in (a, b, w) if t.requires_grad]
    threads = torch.get_num_threads()
    results = []
    try:
        for count in (1, 2, 2, 3):
            torch.set_num_threads(count)
            value = native_sum(a, b, w)
            results.append((value, *torch.autograd.grad((value * value.detach()).sum(), wanted)))
    finally:
        torch.set_num_threads(threads)
    for first, *others in zip(*results, strict=True):
        assert all(torch.equal(first, other) for other in others)


def test_native_does_not_copy_a_broadcast_w(native, monkeypatch):
    a, b, w = operands(SHAPES[2], 6)
    seen = []

    def spy(self: native_exp_sum.ExpSumLibrary, *args: Tensor) -> Tensor:
        seen.append(args)
        raise StopIteration  # enough: the operands are what this test looks at

    monkeypatch.setattr(native_exp_sum.ExpSumLibrary, "forward", spy)
    with pytest.raises(StopIteration):
        native_sum(a, b, w)
    w_seen, offsets = seen[0][2], seen[0][3]
    assert w_seen.data_ptr() == w.data_ptr() and w_seen.stride()[0] == 0
    assert offsets[2].tolist() == [p * 33 * 33 for p in range(10)] * 2
    # The items that share a W slice are visited one after another.
    assert offsets[3].tolist() == list(itertools.chain.from_iterable((p, p + 10) for p in range(10)))


def test_other_dtypes_take_the_torch_path(native):
    a, b, w = (t.float() for t in operands(SHAPES[1], 7))
    reference = weighted_exp_sum(a, b, w)
    assert torch.equal(native_sum(a, b, w), reference)


@pytest.mark.parametrize("backend", ["torch", "native"])
def test_empty_sums_are_zero(built, backend):
    for n, m in [(0, 4), (4, 0)]:
        a, b, w = operands(((2,), (2,), (2,), n, m, 3), 8, requires_grad=True)
        value = weighted_exp_sum(a, b, w, engine=Engine(exp_sums=backend))
        assert torch.equal(value, torch.zeros(2, dtype=DTYPE))
        grads = torch.autograd.grad(value.sum(), (a, b, w), allow_unused=True)
        assert all(g is None or not g.any() for g in grads)


def test_shape_mismatch_is_a_clear_error():
    a, b, w = operands(SHAPES[1], 9)
    with pytest.raises(ValueError, match=r"W `\.\.\. x n x m`"):
        weighted_exp_sum(a, b, w.mT)


def test_moments_agree_across_backends(built, gp_factory, cov_factory):
    model = gp_factory(40, 3, 2, (1,), seed=11)
    cache = model.posterior_cache()
    theta = cache.hyperparameters
    gen = torch.Generator().manual_seed(12)
    mean = (0.5 * torch.randn(2, 6, generator=gen, dtype=DTYPE)).requires_grad_()
    state = Gaussian(mean, cov_factory(6, 0.7, gen, batch=(2,)))
    results = {}
    for name in ("torch", "native"):
        moments = SEKernelMoments(cache.inputs, cache.beta, theta.lengthscales, theta.signal_variance, cache.K_inv,
                                  engine=Engine(exp_sums=name))
        out = moments(state)
        results[name] = (out.mean, out.cov, out.cross_cov, *torch.autograd.grad(out.cov.sum(), mean))
    names = ("mean", "cov", "cross_cov", "d cov/d mean")
    for got, want, what in zip(results["native"], results["torch"], names, strict=True):
        assert_relative(got, want, want.abs().amax(), what)


def test_auto_falls_back_to_torch_and_says_so_once(monkeypatch, caplog, tmp_path):
    monkeypatch.setattr(loader, "library_path", lambda: tmp_path / "missing.so")
    engine_module._log_once.cache_clear()
    with caplog.at_level(logging.INFO, logger=engine_module.__name__):
        assert Engine.resolve("auto", "reference").exp_sums == "torch"
        assert Engine.resolve("auto", "reference").exp_sums == "torch"
    lines = [r.getMessage() for r in caplog.records if r.name == engine_module.__name__]
    assert len(lines) == 1 and "missing.so" in lines[0] and engine_module.BUILD_COMMAND in lines[0]


def test_auto_falls_back_when_the_library_does_not_load(monkeypatch, tmp_path):
    broken = tmp_path / "broken.so"
    broken.write_bytes(b"not a shared library")
    monkeypatch.setattr(loader, "library_path", lambda: broken)
    assert Engine.resolve("auto", "reference").exp_sums == "torch"


def test_native_requested_but_missing_is_a_user_error(monkeypatch, tmp_path):
    monkeypatch.setattr(loader, "library_path", lambda: tmp_path / "missing.so")
    with pytest.raises(UserError, match=r"kernels.backend=native.*qtl.kernels.native.build"):
        Engine.resolve("native", "reference")
    with pytest.raises(UserError, match="one of auto, native, torch"):
        Engine.resolve("fast", "reference")


def test_native_resolves_where_the_library_loads(built):
    assert Engine.resolve("native", "reference") == Engine(exp_sums="native")
    assert Engine.resolve("torch", "reference") == Engine()
    with pytest.raises(ValueError, match=r"Engine\.exp_sums must be one of native, torch"):
        Engine(exp_sums="auto")


# The lower form (`qtl_exp_sum_forward_lower`, used by se_moments.c for its a = b pairs): when S = A Bᵀ is
# symmetric, Σ_{j<i} (W_ij + W_ji) E_ij + Σ_i W_ii E_ii is the same sum from half the entries.


def symmetric_problem(items: int, n: int, k: int, seed: int) -> tuple[Tensor, ...]:
    """X `items x n x k`, M `items x k x k` symmetric, A = X M, B = X (S = X M Xᵀ symmetric), W not symmetric."""
    gen = torch.Generator().manual_seed(seed)
    x = 0.3 * torch.randn(items, n, k, generator=gen, dtype=DTYPE)
    root = torch.randn(items, k, k, generator=gen, dtype=DTYPE) / k**0.5
    m = 0.5 * (root + root.mT)
    w = torch.randn(items, n, n, generator=gen, dtype=DTYPE)
    return x, m, x @ m, x, w


def library_forward(a: Tensor, b: Tensor, w: Tensor, lower: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """The library's sums, G_A and G_B for dense batches `items x ...` (items visited in order)."""
    batch = a.shape[:-2]
    offsets = (*(native_exp_sum.item_offsets(t, batch) for t in (a, b, w)), torch.arange(batch.numel()))
    return native_exp_sum.load_exp_sum().forward(a, b, w, offsets, (True, True), lower)


def max_relative(got: Tensor, want: Tensor) -> float:
    """max |got − want| over max |want|."""
    return float((got - want).abs().max() / want.abs().max())


# n: one entry, below a row block, across the column chunk (128), the row split (256) and both.
@pytest.mark.parametrize("n", [1, 2, 7, 9, 128, 129, 257, 300, 520])
def test_lower_form_is_the_full_sum_with_the_same_chain_rule(built, n):
    x, m, a, b, w = symmetric_problem(3, n, 6, seed=n)
    flags = torch.tensor([True, False, True])
    full, full_a, full_b = library_forward(a, b, w)
    low, low_a, low_b = library_forward(a, b, w, flags)
    # An item not flagged: the full form, bit for bit.
    assert torch.equal(low[1], full[1]) and torch.equal(low_a[1], full_a[1]) and torch.equal(low_b[1], full_b[1])
    lower = flags.nonzero().squeeze(-1)
    e = torch.exp(a @ b.mT)
    scale = (w.abs() * e).sum((-2, -1))
    assert ((low - full).abs() / scale)[lower].max() <= RTOL
    # G_A, G_B of the lower form: P = (W + Wᵀ) ∘ E below the diagonal, W ∘ E on it, 0 above.
    p = torch.tril((w + w.mT) * e, -1) + torch.diag_embed(torch.diagonal(w * e, dim1=-2, dim2=-1))
    assert max_relative(low_a[lower], (p @ b)[lower]) <= RTOL
    assert max_relative(low_b[lower], (p.mT @ a)[lower]) <= RTOL
    # Not the full form's G_A, G_B (n > 1), but through A = X M, B = X the same gradients for X and
    # for M's symmetric part (the perturbations that keep S symmetric).
    if n > 1:
        assert max_relative(low_a[lower], full_a[lower]) > 1e-3
    grad_x = (full_a @ m.mT + full_b)[lower]
    assert max_relative((low_a @ m.mT + low_b)[lower], grad_x) <= RTOL
    grad_m, low_grad_m = (x.mT @ g for g in (full_a, low_a))
    assert max_relative((low_grad_m + low_grad_m.mT)[lower], (grad_m + grad_m.mT)[lower]) <= RTOL


def test_lower_form_is_bit_identical_across_thread_counts(built):
    *_, a, b, w = symmetric_problem(2, 520, 8, seed=3)  # three row splits
    flags = torch.tensor([True, True])
    threads = torch.get_num_threads()
    try:
        results = []
        for count in (1, 2, 3):
            torch.set_num_threads(count)
            results.append(library_forward(a, b, w, flags))
    finally:
        torch.set_num_threads(threads)
    for first, *others in zip(*results, strict=True):
        assert all(torch.equal(first, other) for other in others)


def test_lower_form_needs_square_weights(built):
    a, b, w = operands(((2,), (2,), (2,), 5, 6, 3), 7)
    with pytest.raises(ValueError, match="square weights"):
        library_forward(a, b, w, torch.tensor([False, True]))
    with pytest.raises(ValueError, match="one flag per item"):
        library_forward(a, b, w, torch.tensor([True]))
    library_forward(a, b, w, torch.tensor([False, False]))  # no lower item: any n, m
