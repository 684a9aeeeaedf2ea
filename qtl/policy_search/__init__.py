"""Policy improvement: maximise the predicted return V^π(ψ) by gradients (Algorithm 1, lines 6-9).

Restarts (:mod:`~qtl.policy_search.restarts`) run one after the other, or (``batched``) all at once:
their ψ stacked as a leading restart dimension `R` of the policy (:mod:`qtl.policies.batching`,
:mod:`~qtl.policy_search.batch`), so that one batched rollout evaluates all R predicted returns, and
the gradient of their sum Σ_r V_r, which is block-separable, gives each restart its own gradient. The
batched search starts from the same points as the sequential one, and each restart runs its own
optimiser:

- L-BFGS (:mod:`~qtl.policy_search.lbfgs`): R independent runs of :func:`qtl.lbfgs.lbfgs` (torch's
  L-BFGS, each with its own curvature memory, line search and stopping tests) in lockstep: every
  round, each running restart asks for V and ∇V at one point and one batched rollout answers all of
  them; a restart that stops leaves the batch. Each restart evaluates the points the sequential
  search (``torch.optim.LBFGS``) evaluates;
- Adam (:mod:`~qtl.policy_search.adam`): one Adam over the stacked ψ, which acts per element, so each
  restart follows its own path; sequential runs may follow MC-PILCO's schedule
  (:mod:`~qtl.policy_search.schedules`) and keep their last or a validated ψ (:mod:`~qtl.policy_search.keep`).

So a batched search is the sequential one up to round-off (a batched value equals the plain
policy's to ~1e-15 relative, which could in principle tip a line-search test), except that a
stochastic objective (particles with ``resample_every > 0``) advances its draws once per batched
evaluation, shared by the restarts. Each optimiser takes its settings as one frozen dataclass
(:mod:`~qtl.policy_search.settings`), which ``qtl.build`` makes from the ``optimizer`` config group.
"""

from qtl.policy_search.adam import AdamSearch
from qtl.policy_search.evaluation import INVALID_PSI_ERRORS
from qtl.policy_search.keep import KEEP, SNAPSHOTS
from qtl.policy_search.lbfgs import LBFGSSearch
from qtl.policy_search.restarts import MIN_PERTURBATION_SCALE, RestartingSearch
from qtl.policy_search.result import SearchResult
from qtl.policy_search.settings import AdamSettings, LBFGSSettings, RestartSettings

__all__ = [
    "INVALID_PSI_ERRORS",
    "KEEP",
    "MIN_PERTURBATION_SCALE",
    "SNAPSHOTS",
    "AdamSearch",
    "AdamSettings",
    "LBFGSSearch",
    "LBFGSSettings",
    "RestartSettings",
    "RestartingSearch",
    "SearchResult",
]
