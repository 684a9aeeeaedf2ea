"""Evidence maximisation of θ for the GP dynamics model: the log evidence, cold and warm-started L-BFGS fits."""

from __future__ import annotations

import contextlib
import logging
import math

import gpytorch
import torch
from linear_operator.utils.errors import NotPSDError
from torch import Tensor

from qtl import health
from qtl.models.exact_settings import exact_gp_settings
from qtl.models.hyperparameters import GPHyperparameters

log = logging.getLogger(__name__)

# Fitting defaults.
DEFAULT_RESTARTS = 3
DEFAULT_MAX_ITER = 100
# L-BFGS stops when the objective (log evidence per data point) changes by less than this.
FIT_TOLERANCE_CHANGE = 1e-6
# L-BFGS runs resumed from the best θ after a trial θ of the line search failed numerically, per fit run.
FIT_RESUMES = 2
# Standard deviation of the log-space perturbation of θ at each extra restart.
RESTART_LOG_SCALE = 0.5
# Warm start: an output whose warm objective (log evidence per point) falls more than this below the
# previous episode's gets the cold restarts (docs/benchmarks.md, GP section, for the figures behind it).
WARM_RESTART_TOLERANCE = 0.05


class GPEvidence:
    """Evidence maximisation for :class:`~qtl.models.DynamicsGP` (a mixin): log evidence, ``fit``, ``fit_warm``."""

    def evidence_settings(self) -> contextlib.AbstractContextManager[None]:
        """The GPyTorch settings of :meth:`log_evidence`: exact Cholesky solves and log-determinants."""
        return exact_gp_settings()

    def log_evidence(self) -> Tensor:
        """Per-output log marginal likelihood plus log priors, divided by n: `E`."""
        return self.gpytorch_log_evidence()

    def gpytorch_log_evidence(self) -> Tensor:
        """:meth:`log_evidence` as GPyTorch's ``ExactMarginalLogLikelihood`` evaluates it (training mode): `E`."""
        mll = gpytorch.mlls.ExactMarginalLogLikelihood(self.likelihood, self)
        with self.evidence_settings():
            return mll(self(*self.train_inputs), self.train_targets)

    def log_prior(self) -> Tensor:
        """The registered priors' log densities per output `E`, summed as GPyTorch's marginal likelihood sums them."""
        total = torch.zeros(self.num_outputs, dtype=self.train_x.dtype, device=self.train_x.device)
        for _, module, prior, closure, _ in self.named_priors():
            term = prior.log_prob(closure(module))
            total = total + term.view(*term.shape[:1], -1).sum(-1)
        return total

    def fit(
        self,
        *,
        restarts: int = DEFAULT_RESTARTS,
        max_iter: int = DEFAULT_MAX_ITER,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """Evidence maximisation: L-BFGS from the current θ and ``restarts − 1`` perturbations of it.

        Each output dimension keeps the θ of its best restart (the objective is separable over
        outputs). Returns the final per-output objective `E` (log evidence + log prior, / n).
        """
        if restarts < 1:
            raise ValueError(f"restarts must be >= 1, got {restarts}")
        start = self.hyperparameters
        best_theta = start.log().clone()  # E x (D + 2)
        best_value = torch.full((self.num_outputs,), -math.inf, dtype=best_theta.dtype, device=best_theta.device)
        for attempt in range(restarts):
            log_theta = start.log()
            if attempt > 0:
                noise = torch.randn(
                    log_theta.shape, generator=generator, dtype=log_theta.dtype
                ).to(log_theta.device)
                log_theta = log_theta + RESTART_LOG_SCALE * noise
            try:
                self.hyperparameters = GPHyperparameters.from_log(log_theta)
                value = self._optimise(max_iter)
            except (NotPSDError, ValueError, RuntimeError) as err:
                health.count(health.GP_FIT_FAILED)
                log.info("GP fit restart %d failed and is discarded: %s", attempt, err)
                continue
            found = self.hyperparameters.log()
            better = torch.isfinite(value) & (value > best_value)
            best_theta[better] = found[better]
            best_value = torch.where(better, value, best_value)
        return self._keep_best(best_theta, best_value)

    def fit_warm(
        self,
        start: GPHyperparameters,
        reference: Tensor,
        *,
        restarts: int = DEFAULT_RESTARTS,
        max_iter: int = DEFAULT_MAX_ITER,
        generator: torch.Generator | None = None,
        tolerance: float = WARM_RESTART_TOLERANCE,
    ) -> Tensor:
        """Evidence maximisation from ``start`` (the previous θ_p); cold restarts only where it falls short.

        One L-BFGS run from ``start``; an output whose objective is below ``reference`` `E` (the
        previous fit's objective per point) minus ``tolerance``, or not finite, is refitted as
        :meth:`fit` does from the current θ (the cold start: heuristic or θ_s) and its perturbations,
        on a model of those outputs alone (the objective is separable over outputs); each output keeps
        the better θ (every output short: the cold fit of this model). No output short: no restart runs.
        Returns the per-output objective `E`.
        """
        cold = self.hyperparameters
        cold_state = {name: value.clone() for name, value in self.state_dict().items()}  # θ bit for bit
        try:
            self.hyperparameters = start
            value = self._optimise(max_iter)
        except (NotPSDError, ValueError, RuntimeError) as err:
            health.count(health.GP_FIT_FAILED)
            log.info("warm-started GP fit failed, every output is refitted cold: %s", err)
            value = torch.full((self.num_outputs,), -math.inf, dtype=cold.lengthscales.dtype,
                               device=cold.lengthscales.device)
        best = self.hyperparameters.log() if torch.isfinite(value).any() else cold.log()
        short = ~torch.isfinite(value) | (value < reference.to(value) - tolerance)
        if short.any():
            chosen = short.nonzero().flatten()
            log.info("warm GP fit short of the previous objective for output(s) %s: cold restarts there",
                     chosen.tolist())
            if short.all():  # every output: the cold fit of this model, from exactly its cold θ
                self.load_state_dict(cold_state)
                self.prediction_strategy = None
                part = self
            else:
                extra = None if self.extra_noise is None else self.extra_noise[chosen].T  # n x |chosen|
                part = type(self)(self.train_x, self.train_y[:, chosen], cold.select(chosen), extra_noise=extra,
                                  dtype=self.train_x.dtype)
            try:
                part_value = part.fit(restarts=restarts, max_iter=max_iter, generator=generator)
            except RuntimeError as err:
                health.count(health.GP_FIT_FAILED)
                log.info("cold restarts failed: %s", err)
                part_value = torch.full_like(value[chosen], -math.inf)
            better = torch.isfinite(part_value) & (part_value > value[chosen])
            log.info("cold restarts: the cold fit kept for output(s) %s, the warm fit for %s",
                     chosen[better].tolist(), chosen[~better].tolist())
            if part is self and better.all():  # the cold fit won everywhere: keep its θ as it left it
                return part_value
            best[chosen[better]] = part.hyperparameters.log()[better]
            value[chosen[better]] = part_value[better]
        return self._keep_best(best, value)

    def _keep_best(self, log_theta: Tensor, value: Tensor) -> Tensor:
        """Set θ from the best log θ `E x (D + 2)` and return its objective `E`; an error where an output has none."""
        if not torch.isfinite(value).all():
            failed = (~torch.isfinite(value)).nonzero().flatten().tolist()
            raise RuntimeError(f"evidence maximisation failed for output dimension(s) {failed}")
        self.hyperparameters = GPHyperparameters.from_log(log_theta)
        self.fit_objective = value
        return value

    def _optimise(self, max_iter: int) -> Tensor:
        """L-BFGS on the summed objective for at most ``max_iter`` iterations; returns the per-output objective `E`.

        A trial θ of the line search whose objective fails numerically (a factorisation error, or a
        non-finite value; e.g. a step to ℓ ~ e⁻²⁰⁰ on a flat direction) does not end the run: the θ of
        the best objective evaluated is restored and a fresh L-BFGS (its first step short) goes on with
        the iterations left, at most ``FIT_RESUMES`` times. A failure before any finite objective raises.
        """
        self.train()
        self.likelihood.train()
        params = [p for p in self.parameters() if p.requires_grad]
        best: list = [-math.inf, None]  # the best summed objective evaluated, and its parameters

        def closure() -> Tensor:
            optimiser.zero_grad()
            total = self.log_evidence().sum()
            value = float(total.detach())
            if not math.isfinite(value):
                raise RuntimeError(f"the log evidence is not finite ({value})")
            (-total).backward()
            if value > best[0]:
                best[0], best[1] = value, [p.detach().clone() for p in params]
            return -total

        left = max_iter
        for resume in range(FIT_RESUMES + 1):
            optimiser = torch.optim.LBFGS(
                params, lr=1.0, max_iter=left, line_search_fn="strong_wolfe",
                tolerance_change=FIT_TOLERANCE_CHANGE,
            )
            try:
                optimiser.step(closure)
                break
            except (NotPSDError, ValueError, RuntimeError) as err:
                if best[1] is None:
                    raise
                left -= optimiser.state[params[0]].get("n_iter", 0)
                health.count(health.GP_FIT_FAILED)
                with torch.no_grad():
                    for param, value in zip(params, best[1], strict=True):
                        param.copy_(value)
                if resume == FIT_RESUMES or left <= 0:
                    log.info("GP fit: a line-search step failed (%s); it ends at the best θ evaluated", err)
                    break
                log.info("GP fit: a line-search step failed (%s); L-BFGS resumes from the best θ evaluated "
                            "(%d iterations left)", err, left)
        with torch.no_grad():
            value = self.log_evidence()
        self.eval()
        self.likelihood.eval()
        return value.detach()
