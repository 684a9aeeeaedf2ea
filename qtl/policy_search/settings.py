"""The optimisers' settings: one frozen dataclass per search, each option checked with a one-line error."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from qtl.lbfgs import LBFGSOptions
from qtl.plateau import PlateauRule
from qtl.policy_search.keep import KEEP


@dataclass(frozen=True, kw_only=True)
class RestartSettings:
    """The restarts of a search: ``restarts`` runs in all, the later ones from ψ perturbed by ``perturbation``.

    ``batched``: all restarts at once, their ψ stacked in one rollout, where the search can (see its ``batched``).
    """

    restarts: int = 1
    perturbation: float = 0.1
    batched: bool = False

    def __post_init__(self) -> None:
        if self.restarts < 1:
            raise ValueError(f"restarts must be >= 1, got {self.restarts}")
        if self.perturbation < 0:
            raise ValueError(f"perturbation must be >= 0, got {self.perturbation}")


@dataclass(frozen=True, kw_only=True)
class LBFGSSettings(RestartSettings):
    """L-BFGS's settings: ``max_iter`` iterations and evaluations per run, and the restarts."""

    max_iter: int = 100
    restarts: int = 2

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.max_iter < 1:
            raise ValueError(f"max_iter must be >= 1, got {self.max_iter}")

    @property
    def options(self) -> LBFGSOptions:
        """The options of each run's :func:`qtl.lbfgs.lbfgs`: torch.optim.LBFGS's, ``max_iter`` evaluations too."""
        return LBFGSOptions(max_iter=self.max_iter, max_eval=self.max_iter)


@dataclass(frozen=True, kw_only=True)
class AdamSettings(RestartSettings):
    """Adam's settings: ``steps`` steps per run at learning rate ``lr``, the ψ a run leaves, MC-PILCO's schedule.

    ``keep``: one of :data:`~qtl.policy_search.keep.KEEP`. The schedule
    (:class:`~qtl.policy_search.schedules.Schedule`): ``dropout`` p of the policy's basis functions, and
    with a ``plateau`` rule (a :class:`~qtl.plateau.PlateauRule`, or its fields as a mapping) the learning
    rate × ``lr_reduction`` (not below ``lr_min``) and p − ``dropout_reduction`` at each plateau.
    ``lr_scales``: a factor on the learning rate per part of ψ, by its own name (e.g. ``centres``).
    """

    steps: int = 300
    lr: float = 0.01
    keep: str = "best"
    dropout: float = 0.0
    dropout_reduction: float = 0.125
    plateau: PlateauRule | None = None
    lr_reduction: float = 0.5
    lr_min: float = 0.0025
    lr_scales: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.steps < 1 or self.lr <= 0:
            raise ValueError(f"steps must be >= 1 and lr > 0, got {self.steps} and {self.lr}")
        if self.keep not in KEEP:
            raise ValueError(f"keep must be one of {', '.join(KEEP)}, got {self.keep!r}")
        if not 0.0 <= self.dropout < 1.0 or self.dropout_reduction < 0:
            raise ValueError(f"dropout must be in [0, 1) and dropout_reduction >= 0, got {self.dropout} and "
                             f"{self.dropout_reduction}")
        if not 0.0 < self.lr_reduction <= 1.0 or not 0.0 <= self.lr_min <= self.lr:
            raise ValueError(f"lr_reduction must be in (0, 1] and lr_min in [0, lr], got {self.lr_reduction} and "
                             f"{self.lr_min}")
        if self.plateau is not None and not isinstance(self.plateau, PlateauRule):
            self._set("plateau", PlateauRule(**self.plateau))
        if self.scheduled and self.batched and self.restarts > 1:
            raise ValueError("optimizer.keep=last, optimizer.dropout and optimizer.plateau run restarts one after "
                             "the other: set optimizer.batched=false or optimizer.restarts=1")
        for name in ("dropout", "dropout_reduction", "lr_reduction", "lr_min"):
            self._set(name, float(getattr(self, name)))
        self._set("lr_scales", {str(k): float(v) for k, v in self.lr_scales.items()})
        if any(not v > 0 for v in self.lr_scales.values()):
            raise ValueError(f"lr_scales must be > 0, got {self.lr_scales}")

    def _set(self, name: str, value: object) -> None:
        """Normalise a field of this frozen instance while it is checked."""
        object.__setattr__(self, name, value)

    @property
    def scheduled(self) -> bool:
        """Whether a run follows a schedule (``keep`` other than best, dropout, or a plateau rule)."""
        return self.keep != "best" or self.dropout > 0 or self.plateau is not None
