"""Gaussian state distributions, the moment-matched image of a map applied to one, and per-element factorisations.

A batched rollout (restarts `R` searched together) factorises covariances of every batch element at once. Outside
:func:`element_failures` a factorisation that fails for any element raises ``torch.linalg.LinAlgError``, as
``torch.linalg.cholesky`` does; inside, the failed elements' results are NaN (so their values are not finite) and
their masks are listed, while the other elements are computed exactly as they would be without them.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

import torch
from torch import Tensor


def batch_shapes(*shapes: torch.Size) -> torch.Size:
    """``torch.broadcast_shapes(*shapes)``; no Python-level broadcasting where each shape is the longest one's tail."""
    if not shapes:
        return torch.Size()
    longest = max(shapes, key=len)
    size = len(longest)
    if all(shape == longest[size - len(shape) :] for shape in shapes):
        return torch.Size(longest)
    return torch.broadcast_shapes(*shapes)


@dataclass(frozen=True)
class Gaussian:
    """N(mean, cov) with leading batch dimensions: ``mean`` `... x D`, ``cov`` `... x D x D`.

    The batch shapes of ``mean`` and ``cov`` need only broadcast against each other.
    """

    mean: Tensor
    cov: Tensor

    def __post_init__(self) -> None:
        if self.mean.dim() < 1:
            raise ValueError("mean must be at least 1-D (`... x D`)")
        dim = self.mean.shape[-1]
        if self.cov.dim() < 2 or self.cov.shape[-2:] != (dim, dim):
            raise ValueError(
                f"cov must be `... x {dim} x {dim}` to match mean {tuple(self.mean.shape)}, got {tuple(self.cov.shape)}"
            )
        batch_shapes(self.mean.shape[:-1], self.cov.shape[:-2])  # raises if not

    @property
    def dim(self) -> int:
        """D, the dimension of the random vector."""
        return self.mean.shape[-1]

    @property
    def batch_shape(self) -> torch.Size:
        """The broadcast batch shape of mean and covariance."""
        return batch_shapes(self.mean.shape[:-1], self.cov.shape[:-2])

    @property
    def dtype(self) -> torch.dtype:
        """The dtype of the mean."""
        return self.mean.dtype

    def expand(self) -> Gaussian:
        """The same distribution with mean and covariance broadcast to the full batch shape."""
        batch = self.batch_shape
        return Gaussian(self.mean.expand(*batch, self.dim), self.cov.expand(*batch, self.dim, self.dim))

    def __getitem__(self, index: int | slice | tuple) -> Gaussian:
        """Index the batch dimensions (both tensors are broadcast to the batch shape first)."""
        full = self.expand()
        return Gaussian(full.mean[index], full.cov[index])

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> Gaussian:
        """The same distribution on another dtype/device."""
        return Gaussian(self.mean.to(device=device, dtype=dtype), self.cov.to(device=device, dtype=dtype))

    def sample(self, num_samples: int, generator: torch.Generator | None = None) -> Tensor:
        """Draw samples `num_samples x ... x D`; a singular (PSD) covariance is allowed."""
        batch = self.batch_shape
        # A symmetric square root tolerates singular covariances, unlike a Cholesky factor.
        root = symmetric_root(self.expand().cov)
        noise = torch.randn((num_samples, *batch, self.dim), generator=generator, dtype=self.dtype).to(self.mean.device)
        return self.mean + (root @ noise[..., None]).squeeze(-1)


@dataclass(frozen=True)
class MomentMatch:
    """Moment-matched image of a map f of a Gaussian input x ~ N(μ, Σ).

    ``mean`` `... x F` is E[f(x)], ``cov`` `... x F x F` is cov[f(x)], ``cross_cov``
    `... x D x F` is cov[x, f(x)], and ``gain`` `... x D x F` is Σ⁻¹ cov[x, f(x)] — by Stein's
    lemma the expected Jacobian E[∂f/∂x]ᵀ, PILCO's ``C``. The gain is what chains
    covariances through a sequence of maps without ever inverting a (possibly singular) Σ.
    """

    mean: Tensor
    cov: Tensor
    cross_cov: Tensor
    gain: Tensor

    @property
    def output(self) -> Gaussian:
        """The moment-matched Gaussian of f(x)."""
        return Gaussian(self.mean, self.cov)


# A map of Gaussian inputs with exact (or moment-matched) output moments.
GaussianMap = Callable[[Gaussian], MomentMatch]


def full_batch(state: Gaussian) -> Gaussian:
    """``state`` when mean and covariance already have the full batch shape, else ``state.expand()``.

    Unlike ``expand`` it adds no (view) operation to the autograd graph when there is nothing to
    broadcast, which changes the order gradients accumulate in: round-off only.
    """
    if state.mean.shape[:-1] == state.cov.shape[:-2]:
        return state
    return state.expand()


@functools.lru_cache(maxsize=64)
def identity(dim: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """The `dim x dim` identity, created once per (dim, dtype, device): read-only, never write into it."""
    return torch.eye(dim, dtype=dtype, device=device)


def batch_matmul(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b`` for `... x m x k` and `... x k x p` of equal batch shapes as one ``bmm`` (fewer dispatched views)."""
    batch = a.shape[:-2]
    if batch != b.shape[:-2]:
        return a @ b
    if not batch:
        return torch.mm(a, b)
    if len(batch) == 1:  # bmm as it is: no reshape views
        return torch.bmm(a, b)
    out = torch.bmm(a.reshape(-1, *a.shape[-2:]), b.reshape(-1, *b.shape[-2:]))
    return out.view(*batch, *out.shape[-2:])


def symmetrize(cov: Tensor) -> Tensor:
    """(Σ + Σᵀ)/2 for `... x D x D`: removes round-off asymmetry."""
    return 0.5 * (cov + cov.mT)


def symmetric_root(cov: Tensor) -> Tensor:
    """The PSD square root L = V Λ^{1/2} (L Lᵀ = Σ) of a symmetric PSD `... x D x D`; singular Σ allowed."""
    eigval, eigvec = torch.linalg.eigh(symmetrize(cov))
    return eigvec * eigval.clamp_min(0.0).sqrt()[..., None, :]


def matrix_root(cov: Tensor) -> Tensor:
    """L with L Lᵀ = Σ for `... x D x D`: the Cholesky factor, or :func:`symmetric_root` if any Σ is singular."""
    chol, info = torch.linalg.cholesky_ex(cov)
    if bool((info == 0).all()):
        return chol
    return symmetric_root(cov)


def sample_moments(samples: Tensor, dim: int = -2) -> Gaussian:
    """Sample mean and unbiased covariance over the sample dimension ``dim`` of `... x D` (not the last).

    E.g. particles `... x P x D` give mean `... x D` and cov `... x D x D`; paths `... x P x T x D`
    with ``dim=-3`` give mean `... x T x D` and cov `... x T x D x D`.
    """
    if samples.dim() < 2 or dim % samples.dim() == samples.dim() - 1:
        raise ValueError(f"samples must be `... x D` with the sample dimension {dim} before D, "
                         f"got {tuple(samples.shape)}")
    mean = samples.mean(dim)
    centred = (samples - mean.unsqueeze(dim)).movedim(dim, -2)  # ... x P x D
    cov = torch.einsum("...pd,...pe->...de", centred, centred) / (samples.shape[dim] - 1)
    return Gaussian(mean, symmetrize(cov))


def compose(inner: MomentMatch, outer: MomentMatch) -> MomentMatch:
    """Moments of g(f(x)) from those of f(x) and of g at N(E f, cov f), joint-Gaussian chaining.

    cov[x, g] = cov[x, f] Σ_f⁻¹ cov[f, g]: exact when x and f(x) are jointly Gaussian, and the
    approximation PILCO's ``propagate`` makes otherwise.
    """
    return MomentMatch(
        mean=outer.mean,
        cov=outer.cov,
        cross_cov=inner.cross_cov @ outer.gain,
        gain=inner.gain @ outer.gain,
    )


# The failed-element masks of the current :func:`element_failures` block (None: failures raise).
_FAILURES: ContextVar[list[Tensor] | None] = ContextVar("qtl_element_failures", default=None)
NOT_PD = "the factorization could not be completed because the input is not positive-definite"


@contextmanager
def element_failures() -> Iterator[list[Tensor]]:
    """Inside, a factorisation failing for some batch elements makes their results NaN; yields their masks `...`."""
    masks: list[Tensor] = []
    token = _FAILURES.set(masks)
    try:
        yield masks
    finally:
        _FAILURES.reset(token)


def failed_elements(failed: Tensor, inner: int = 0, what: str = "linalg.cholesky") -> Tensor | None:
    """``failed`` `... x *inner` (nonzero: failed, e.g. ``info``) as a mask, each element `...` set wholly; or None.

    An element fails where any of its parts did. Outside :func:`element_failures` a failure raises
    ``torch.linalg.LinAlgError``; inside, the element mask `...` is recorded.
    """
    if not bool(failed.any()):
        return None
    masks = _FAILURES.get()
    if masks is None:
        raise torch.linalg.LinAlgError(f"{what}: {NOT_PD}")
    failed = failed != 0
    element = failed.flatten(failed.dim() - inner).any(-1) if inner else failed
    masks.append(element)
    return element.reshape(*element.shape, *(1,) * inner).expand(failed.shape)


def cholesky(mat: Tensor, inner: int = 0) -> tuple[Tensor, Tensor | None]:
    """(L, failed): the Cholesky factor of symmetric `... x D x D` and the mask `...` of failed ones (None: none).

    ``inner``: how many trailing batch dimensions belong to one element (all of its matrices fail together).
    A failed matrix is factorised as the identity (L = I, finite, gradient zero): its caller makes its results
    NaN by :func:`nan_where`. Outside :func:`element_failures` a failure raises instead.
    """
    chol, info = torch.linalg.cholesky_ex(mat)
    failed = failed_elements(info, inner)
    if failed is None:
        return chol, None
    eye = identity(mat.shape[-1], mat.dtype, mat.device)
    return torch.linalg.cholesky(torch.where(failed[..., None, None], eye, mat)), failed


def nan_where(failed: Tensor | None, value: Tensor) -> Tensor:
    """``value`` `... x *rest` with NaN where ``failed`` `...` is set (as is when ``failed`` is None)."""
    if failed is None:
        return value
    mask = failed.reshape(*failed.shape, *(1,) * (value.dim() - failed.dim()))
    return value.masked_fill(mask, float("nan"))
