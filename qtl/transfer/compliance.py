"""Task compliance Λ (Eq. 14): how well the source dynamics GP explains the target's transitions.

Both are computed on the outputs the two GPs learn: the modelled outputs (all but the positions under speed
integration), less any either modelled as deterministic (a constant Δ in its data, :mod:`qtl.models.constant`).

The source definition, Lazaric, Restelli & Bonarini (ICML 2008), as the public reimplementation in
trlib (github.com/AndreaTirinzoni/iw-transfer-rl, ``lazaric2008.py``) has it; the paper's own text
was not at hand, see ``docs/dev/compliance-notes.md`` for what is known and from where. A target tuple
τ_i = ⟨s_i, a_i, s'_i, r_i⟩ is compared with the source tuples ⟨s_j, a_j, s'_j, r_j⟩ through
Gaussian kernels φ_δ(d) = exp(−d²/δ). Weights w_ij ∝ φ_δsa(‖(s_i, a_i) − (s_j, a_j)‖), normalised
over the source tuples j, pick the source tuples near the target's state-action; the transition
factor is Σ_j w_ij φ_δs'(‖s'_i − (s_i + s'_j − s_j)‖), the kernel between the two displacements;
the reward factor is Σ_j w_ij φ_δr(|r_i − r_j|) (that code also divides both by the number of
source tuples). Their product is the compliance λ_i ∝ P(S | τ_i)
of the tuple; times the prior P(S) and averaged over the target tuples it is the task compliance
(Eq. 14), which that code then normalises over the candidate source tasks. With one source and a
known reward shared by both tasks only the transition factor remains.

Two estimates live here. :func:`kernel_compliance` follows that definition with the source GP in
place of the kernel regression: its predictive mean replaces the weighted source displacements,
its predictive variance (noise included) plus the kernel's bandwidth (below) is the width, and λ_i
is that density of Δ_i relative to its mode, a value in (0, 1] that is 1 where the source predicts
Δ_i exactly; it is the default. :func:`task_compliance` compares two hypotheses with equal prior instead:
the source GP generated Δ_j (its predictive, noise included) or the target GP did (its
leave-one-out predictive, so that the target does not explain its own data trivially); Λ is the
mean over j of the tempered posterior probability of the source hypothesis.

The kernel estimate's width. Lazaric et al.'s transition factor is a kernel density estimate of
the target's displacement from the source's displacements, and a kernel density estimate needs a
bandwidth. :func:`kernel_compliance` takes Scott's rule (``bandwidth="scott"``, the default, as
``scipy.stats.gaussian_kde``): h_a = σ̂_a m^(−1/(E+4)), σ̂_a the standard deviation of output a's
Δ over the source's m tuples; smoothing the source GP's predictive N(μ, v) with N(0, h_a²) gives
N(μ, v + h_a²). It depends on the source's data only, so one scale serves every target.
``bandwidth="none"`` keeps the GP's predictive alone: on our near-deterministic simulators v is
tiny and Λ is then near 0 on every target but the source task itself (``docs/dev/compliance-notes.md``).

On near-deterministic simulators both predictive variances are tiny, each tuple's log-likelihood
ratio is in the hundreds and the two-hypothesis Λ saturates at 0 or 1 whatever κ. ``resolution``
ρ compares at a finite resolution instead: ρ² s_a² (s_a the standard deviation of output a's Δ
over the target tuples) is added to every predictive variance, so that a source prediction off by
less than about ρ s_a counts as explaining the tuple.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from qtl.models import DynamicsGP

# log(2π), the constant of a Gaussian log density.
LOG_TWO_PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class Compliance:
    """Task compliance Λ and its per-tuple terms (Eq. 14).

    ``value``: Λ, the mean of ``probabilities``; ``probabilities``: `n`, P(S | τ_j);
    ``log_source``: `n`, log p_S(j); ``log_target``: `n`, log p_T(j) (leave-one-out);
    ``temperature``: κ, the tempering of the log-likelihood ratio; ``resolution``: ρ.
    """

    value: float
    probabilities: Tensor
    log_source: Tensor
    log_target: Tensor
    temperature: float
    resolution: float = 0.0


def _gaussian_log_density(y: Tensor, mean: Tensor, variance: Tensor) -> Tensor:
    """Elementwise log N(y; mean, variance) for Eq. 14, all of one shape."""
    return -0.5 * (LOG_TWO_PI + variance.log() + (y - mean).square() / variance)


def leave_one_out(model: DynamicsGP) -> tuple[Tensor, Tensor]:
    """Leave-one-out predictive means and variances `n x E` of the model's own training targets (Eq. 14)."""
    cache = model.exact().posterior_cache()  # leave-one-out needs the n x n solve, not a sparse form
    precision = torch.diagonal(cache.K_inv, dim1=-2, dim2=-1)  # E x n, [K_y⁻¹]_ii
    mean = model.train_y - (cache.beta / precision).T  # n x E, y_i − [K_y⁻¹y]_i / [K_y⁻¹]_ii
    variance = precision.reciprocal().T  # n x E, 1 / [K_y⁻¹]_ii
    return mean, variance


def _shared_outputs(source: DynamicsGP, target: DynamicsGP) -> tuple[list[int] | slice, list[int] | slice]:
    """The columns of the outputs both GPs learn, in the target's order: the source's and the target's (Eq. 14).

    All of them (as slices) when the GPs learn the same outputs; else those they share, an output one of them
    modelled as deterministic (its Δ constant in its data, :mod:`qtl.models.constant`) left out. Different input
    dimensions or modelled outputs (learned or deterministic), or no learned output in common, raise ValueError.
    """
    modelled = [sorted(m.outputs + m.constant_outputs) for m in (source, target)]
    if source.input_dim != target.input_dim or modelled[0] != modelled[1]:
        raise ValueError(
            f"source GP has D={source.input_dim} inputs and E={source.num_outputs} outputs, "
            f"target GP has D={target.input_dim} inputs and E={target.num_outputs} outputs: "
            f"task compliance needs the same GP input dimension and modelled outputs (source {modelled[0]}, "
            f"target {modelled[1]})"
        )
    if source.outputs == target.outputs:
        return slice(None), slice(None)
    shared = [d for d in target.outputs if d in source.outputs]
    if not shared:
        raise ValueError(f"source GP learns outputs {list(source.outputs)}, target GP {list(target.outputs)} (the "
                         "others are deterministic): no output in common for task compliance")
    return [source.outputs.index(d) for d in shared], [target.outputs.index(d) for d in shared]


def _check_resolution(resolution: float) -> None:
    """Raise unless the resolution ρ is finite and >= 0 (Eq. 14)."""
    if not (math.isfinite(resolution) and resolution >= 0):
        raise ValueError(f"resolution must be finite and >= 0, got {resolution}")


def _resolution_floor(deltas: Tensor, resolution: float) -> Tensor:
    """ρ² s_a², `E`: the variance added at resolution ρ, s_a the spread of output a's Δ over the tuples."""
    if deltas.shape[0] > 1:
        return resolution**2 * deltas.var(dim=0, correction=0)
    return torch.zeros_like(deltas[0])


def task_compliance(
    source: DynamicsGP, target: DynamicsGP, *, temperature: float | None = None, resolution: float = 0.0
) -> Compliance:
    """Task compliance Λ of the target model's training tuples under the source model (Eq. 14)."""
    source_cols, target_cols = _shared_outputs(source, target)
    inputs, deltas = target.train_x, target.train_y[:, target_cols]  # n x D, n x E (the outputs both GPs learn)
    kappa = float(deltas.shape[-1] if temperature is None else temperature)
    if not (math.isfinite(kappa) and kappa > 0):
        raise ValueError(f"temperature must be finite and > 0, got {temperature}")
    _check_resolution(resolution)

    floor = _resolution_floor(deltas, resolution)  # E
    # log p_S(j): the source GP's predictive, its own data and θ, noise included.
    source_mean, source_var = (t[:, source_cols] for t in source.predict(inputs, include_noise=True))  # n x E each
    log_source = _gaussian_log_density(deltas, source_mean.to(deltas), source_var.to(deltas) + floor).sum(-1)  # n
    # log p_T(j): the target GP's leave-one-out predictive.
    loo_mean, loo_var = (t[:, target_cols] for t in leave_one_out(target))  # n x E each
    log_target = _gaussian_log_density(deltas, loo_mean, loo_var + floor).sum(-1)  # n
    # P(S | τ_j) = logistic((log p_S − log p_T) / κ); Λ = mean over j (Eq. 14).
    probabilities = torch.sigmoid((log_source - log_target) / kappa)  # n
    return Compliance(
        value=float(probabilities.mean()),
        probabilities=probabilities,
        log_source=log_source,
        log_target=log_target,
        temperature=kappa,
        resolution=float(resolution),
    )


@dataclass(frozen=True)
class KernelCompliance:
    """Task compliance Λ after Lazaric et al. (2008) and its per-tuple terms (Eq. 14).

    ``value``: Λ, the mean of ``probabilities``; ``probabilities``: `n`, λ_i ∝ P(S | τ_i), each in
    (0, 1]; ``log_kernel``: `n x E`, log of output a's kernel factor of tuple i, −(Δ_ia − μ_ia)² / (2 (v_ia + h_a²));
    ``bandwidth``: `E`, h_a, the kernel density estimate's bandwidth per output (zeros for ``"none"``);
    ``resolution``: ρ.
    """

    value: float
    probabilities: Tensor
    log_kernel: Tensor
    bandwidth: Tensor
    resolution: float = 0.0


# The kernel density estimate's bandwidth rules of :func:`kernel_compliance`.
BANDWIDTHS = ("scott", "none")


def scott_bandwidth(deltas: Tensor) -> Tensor:
    """h_a = σ̂_a m^(−1/(E+4)), `E`: Scott's rule on the source's displacements `m x E` (scipy's gaussian_kde)."""
    m, num_outputs = deltas.shape
    if m < 2:
        return torch.zeros_like(deltas[0])
    return deltas.std(dim=0, correction=1) * m ** (-1.0 / (num_outputs + 4))


def _check_bandwidth(bandwidth: str) -> None:
    """Raise unless ``bandwidth`` names one of :data:`BANDWIDTHS` (Eq. 14)."""
    if bandwidth not in BANDWIDTHS:
        raise ValueError(f"bandwidth must be one of {', '.join(BANDWIDTHS)}, got {bandwidth!r}")


def kernel_compliance(
    source: DynamicsGP, target: DynamicsGP, *, bandwidth: str = "scott", resolution: float = 0.0
) -> KernelCompliance:
    """Task compliance Λ after Lazaric et al., the source GP standing for their kernel estimate (Eq. 14).

    λ_i = Π_a exp(−(Δ_ia − μ_a(z_i))² / (2 (v_a(z_i) + h_a²))): the source GP's predictive mean μ
    and variance v (noise included, plus ρ² s_a² at resolution ρ) stand for the source tuples' weighted
    displacements and their spread, h_a is the kernel's bandwidth (Scott's rule on the source's Δ, or
    0 for ``"none"``). Λ = mean over i of λ_i, the prior P(S) = 1 of a single source. Without a
    bandwidth, for target tuples of the source task itself and a calibrated source, E[λ_i] = 2^(−E/2).
    """
    source_cols, target_cols = _shared_outputs(source, target)
    _check_bandwidth(bandwidth)
    _check_resolution(resolution)

    inputs, deltas = target.train_x, target.train_y[:, target_cols]  # n x D, n x E (the outputs both GPs learn)
    floor = _resolution_floor(deltas, resolution)  # E
    source_deltas = source.train_y[:, source_cols].to(deltas)  # m x E
    width = scott_bandwidth(source_deltas) if bandwidth == "scott" else torch.zeros_like(source_deltas[0])  # E
    mean, variance = (t[:, source_cols] for t in source.predict(inputs, include_noise=True))  # n x E each
    mean, variance = mean.to(deltas), variance.to(deltas) + floor + width.square()
    log_kernel = -0.5 * (deltas - mean).square() / variance  # n x E: log p_S(Δ_ia) − log p_S(μ_ia)
    probabilities = log_kernel.sum(-1).exp()  # n: λ_i, the kernels of the E outputs multiplied
    return KernelCompliance(
        value=float(probabilities.mean()),
        probabilities=probabilities,
        log_kernel=log_kernel,
        bandwidth=width,
        resolution=float(resolution),
    )


# The compliances by name; "kernel" (Lazaric et al.'s definition, Scott's bandwidth) is the default since
# scripts/bench_compliance.py measured it (docs/dev/compliance-notes.md); "likelihood_ratio" is the earlier estimate.
COMPLIANCES: dict[str, Callable[..., Compliance | KernelCompliance]] = {
    "likelihood_ratio": task_compliance,
    "kernel": kernel_compliance,
}
DEFAULT_COMPLIANCE = "kernel"


def compliance_function(name: str = DEFAULT_COMPLIANCE) -> Callable[..., Compliance | KernelCompliance]:
    """The task compliance (Eq. 14) called ``name``: one of :data:`COMPLIANCES`."""
    try:
        return COMPLIANCES[name]
    except KeyError:
        raise ValueError(f"unknown task compliance {name!r}: choose one of {sorted(COMPLIANCES)}") from None


def compliance_value(
    name: str, source: DynamicsGP, target: DynamicsGP, *, bandwidth: str = "scott",
    temperature: float | None = None, resolution: float = 0.0,
) -> float:
    """Λ (Eq. 14) by the compliance called ``name``, each given only the options it takes."""
    if compliance_function(name) is kernel_compliance:
        return kernel_compliance(source, target, bandwidth=bandwidth, resolution=resolution).value
    return task_compliance(source, target, temperature=temperature, resolution=resolution).value
