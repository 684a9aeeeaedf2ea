"""The ``model`` config group: which dynamics GP the loop fits to its tuples, and how (Algorithm 1, line 12)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

from qtl import health
from qtl.models.constant import CONSTANT_DELTA_ATOL, CONSTANT_DELTA_RTOL, OutputSplit, split_outputs
from qtl.models.dynamics_gp import DynamicsGP
from qtl.models.gp_evidence import DEFAULT_MAX_ITER, DEFAULT_RESTARTS
from qtl.models.hyperparameters import GPHyperparameters
from qtl.models.sparse_gp import DEFAULT_INDUCING, DEFAULT_JITTER, SparseDynamicsGP
from qtl.models.warm_start import PreviousFit

log = logging.getLogger(__name__)

# `model=auto`: more tuples than this and the exact GP gives way to the sparse GP.
DEFAULT_SPARSE_ABOVE = 1000


class ModelFit(Protocol):
    """What ``instantiate(cfg.model)`` gives: training pairs in, a fitted dynamics GP out."""

    def fit(
        self,
        inputs: Tensor,
        targets: Tensor,
        *,
        start: GPHyperparameters | None = None,
        generator: torch.Generator | None = None,
        previous: PreviousFit | None = None,
        outputs: Sequence[int] | None = None,
        state_dim: int | None = None,
        extra_noise: Tensor | None = None,
    ) -> DynamicsGP:
        """θ_p by evidence maximisation on inputs `n x (F+U)` and targets Δ `n x E`, from ``start`` or the heuristic.

        With ``warm_start`` on, from the ``previous`` episode's fit where there is one; ``start`` (θ_s of the
        free rule, else None) then is the cold start of the restarts only. So a free-rule run's first fit
        starts from θ_s and each later one from θ_p_{i−1}, itself re-learned from θ_s. ``outputs``: the state
        dimensions the E targets are (default: all, 0..E−1), of a ``state_dim``-D state, recorded on the model.
        ``extra_noise``: c `n x E`, tuple i of output e observed with noise σ_ε² + c_ei (source samples weighted by
        relevance, :mod:`qtl.models.point_noise`); None: σ_ε² for every tuple.
        """
        ...


def _check_fit_budget(restarts: int, max_iter: int) -> None:
    """Restarts and L-BFGS iterations must be positive (checked when the config is instantiated)."""
    if restarts < 1:
        raise ValueError(f"model.restarts must be >= 1, got {restarts}")
    if max_iter < 1:
        raise ValueError(f"model.max_iter must be >= 1, got {max_iter}")


def _check_inducing(inducing: int, jitter: float) -> None:
    """The sparse GP needs at least one inducing input, and a jitter >= 0."""
    if inducing < 1:
        raise ValueError(f"model.inducing must be >= 1, got {inducing}")
    if not jitter >= 0:
        raise ValueError(f"model.inducing_jitter must be >= 0 (a fraction of α², e.g. 1e-6), got {jitter}")


@dataclass(frozen=True)
class ExactFit:
    """The exact GP at every data size: L-BFGS from θ and ``restarts − 1`` perturbations, the best kept."""

    restarts: int = DEFAULT_RESTARTS
    max_iter: int = DEFAULT_MAX_ITER
    warm_start: bool = False

    def __post_init__(self) -> None:
        _check_fit_budget(self.restarts, self.max_iter)

    def fit(
        self,
        inputs: Tensor,
        targets: Tensor,
        *,
        start: GPHyperparameters | None = None,
        generator: torch.Generator | None = None,
        previous: PreviousFit | None = None,
        outputs: Sequence[int] | None = None,
        state_dim: int | None = None,
        extra_noise: Tensor | None = None,
    ) -> DynamicsGP:
        """The exact GP on inputs `n x (F+U)`, targets `n x E`, fitted from ``start`` (None: PILCO's heuristic).

        ``warm_start`` and a ``previous`` fit of at least half these tuples: from its θ_p, ``start``
        being the cold start of the outputs the warm fit leaves short (:meth:`DynamicsGP.fit_warm`).
        """
        targets, split, start = _split(targets, outputs, start, previous)
        model = DynamicsGP(inputs, targets, hyperparameters=start, outputs=split.outputs, state_dim=state_dim,
                           constant_outputs=split.constant_outputs, constant_delta=split.constant_delta,
                           extra_noise=_varying(extra_noise, split), dtype=inputs.dtype)
        warm = _warm_from(previous, model) if self.warm_start else None
        if warm is not None:
            model.fit_warm(warm.theta, warm.objective, restarts=self.restarts, max_iter=self.max_iter,
                           generator=generator)
        else:
            model.fit(restarts=self.restarts, max_iter=self.max_iter, generator=generator)
        return model


def _split(
    targets: Tensor, outputs: Sequence[int] | None, start: GPHyperparameters | None, previous: PreviousFit | None
) -> tuple[Tensor, OutputSplit, GPHyperparameters | None]:
    """The targets `n x E''` and ``start`` θ of the outputs a GP learns, and the split (:mod:`qtl.models.constant`).

    Constant outputs are counted in ``health.csv`` at every fit, and logged when they differ from ``previous``'s.
    """
    split = split_outputs(targets, outputs)
    before = () if previous is None else previous.constant_outputs
    if split.constant_outputs != before:
        log.info("outputs %s: Δ constant in the data (std <= %g + %g |mean|), modelled as deterministic (Δ = %s, "
                 "no variance); the GP learns outputs %s", list(split.constant_outputs), CONSTANT_DELTA_ATOL,
                 CONSTANT_DELTA_RTOL, [round(float(v), 12) for v in split.constant_delta], list(split.outputs))
    if not split.constant_outputs:
        return targets, split, start
    health.count(health.CONSTANT_OUTPUTS, len(split.constant_outputs))
    if start is not None and start.num_outputs == targets.shape[-1]:  # θ of every modelled output: the GP's rows
        start = start.select(torch.tensor(split.varying))
    return targets[:, split.varying], split, start


def _varying(extra_noise: Tensor | None, split: OutputSplit) -> Tensor | None:
    """The extra noise `n x E''` of the outputs a GP learns (None stays None)."""
    if extra_noise is None or not split.constant_outputs:
        return extra_noise
    return extra_noise[:, split.varying]


def _warm_from(previous: PreviousFit | None, model: DynamicsGP) -> PreviousFit | None:
    """The previous fit on ``model``'s device and dtype when it saw enough of its data and its outputs, else None."""
    inputs = model.train_x
    if previous is None or not previous.speaks_for(len(inputs)):
        return None
    if previous.modelled != model.outputs:
        log.info("the previous fit modelled outputs %s, this one %s: a cold fit", list(previous.modelled),
                 list(model.outputs))
        return None
    return previous.to(inputs.dtype, inputs.device)


@dataclass(frozen=True)
class SparseFit:
    """The sparse GP (SGPR) at every data size, with ``inducing`` inducing inputs learned with θ.

    ``inducing_jitter``: K_mm's diagonal jitter as a fraction of α² (:class:`SparseDynamicsGP`).
    """

    restarts: int = DEFAULT_RESTARTS
    max_iter: int = DEFAULT_MAX_ITER
    inducing: int = DEFAULT_INDUCING
    warm_start: bool = False
    inducing_jitter: float = DEFAULT_JITTER

    def __post_init__(self) -> None:
        _check_fit_budget(self.restarts, self.max_iter)
        _check_inducing(self.inducing, self.inducing_jitter)

    def fit(
        self,
        inputs: Tensor,
        targets: Tensor,
        *,
        start: GPHyperparameters | None = None,
        generator: torch.Generator | None = None,
        previous: PreviousFit | None = None,
        outputs: Sequence[int] | None = None,
        state_dim: int | None = None,
        extra_noise: Tensor | None = None,
    ) -> DynamicsGP:
        """The sparse GP on inputs `n x (F+U)`, targets `n x E`; ``generator`` draws Z, then the restarts.

        ``warm_start`` and a ``previous`` fit of at least half these tuples: from its θ_p, and its Z
        where the data only grew and the number of inducing inputs is the same (:meth:`SparseDynamicsGP.fit_warm`).
        """
        targets, split, start = _split(targets, outputs, start, previous)
        model = SparseDynamicsGP(inputs, targets, hyperparameters=start, num_inducing=self.inducing,
                                 generator=generator, jitter=self.inducing_jitter, outputs=split.outputs,
                                 state_dim=state_dim, constant_outputs=split.constant_outputs,
                                 constant_delta=split.constant_delta, extra_noise=_varying(extra_noise, split),
                                 dtype=inputs.dtype)
        warm = _warm_from(previous, model) if self.warm_start else None
        if warm is not None:
            inducing = warm.inducing if warm.num_points <= len(inputs) else None  # data only grew
            model.fit_warm(warm.theta, warm.objective, inducing=inducing, restarts=self.restarts,
                           max_iter=self.max_iter, generator=generator)
        else:
            model.fit(restarts=self.restarts, max_iter=self.max_iter, generator=generator)
        return model


@dataclass(frozen=True)
class AutoFit:
    """The exact GP up to ``sparse_above`` tuples, the sparse GP above (None: always exact)."""

    restarts: int = DEFAULT_RESTARTS
    max_iter: int = DEFAULT_MAX_ITER
    sparse_above: int | None = DEFAULT_SPARSE_ABOVE
    inducing: int = DEFAULT_INDUCING
    warm_start: bool = False
    inducing_jitter: float = DEFAULT_JITTER

    def __post_init__(self) -> None:
        _check_fit_budget(self.restarts, self.max_iter)
        _check_inducing(self.inducing, self.inducing_jitter)
        if self.sparse_above is not None and self.sparse_above < 0:
            raise ValueError(f"model.sparse_above must be >= 0 or null, got {self.sparse_above}")

    def fit(
        self,
        inputs: Tensor,
        targets: Tensor,
        *,
        start: GPHyperparameters | None = None,
        generator: torch.Generator | None = None,
        previous: PreviousFit | None = None,
        outputs: Sequence[int] | None = None,
        state_dim: int | None = None,
        extra_noise: Tensor | None = None,
    ) -> DynamicsGP:
        """:class:`ExactFit` or, above ``sparse_above`` tuples, :class:`SparseFit` on inputs `n x (F+U)`."""
        if self.sparse_above is not None and len(inputs) > self.sparse_above:
            log.info("%d tuples > model.sparse_above=%d: the sparse GP, %d inducing inputs", len(inputs),
                     self.sparse_above, min(self.inducing, len(inputs)))
            chosen: ModelFit = SparseFit(self.restarts, self.max_iter, self.inducing, self.warm_start,
                                         self.inducing_jitter)
        else:
            chosen = ExactFit(self.restarts, self.max_iter, self.warm_start)
        return chosen.fit(inputs, targets, start=start, generator=generator, previous=previous, outputs=outputs,
                           state_dim=state_dim, extra_noise=extra_noise)


def log_evidence(model: DynamicsGP) -> float:
    """Mean over the E outputs of the fitted model's log evidence per data point (priors included)."""
    model.train()
    with torch.no_grad():
        value = float(model.log_evidence().mean())
    model.eval()
    return value
