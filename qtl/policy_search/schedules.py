"""MC-PILCO's schedule of an Adam run: policy dropout, and at each plateau a lower learning rate and dropout.

Amadio et al. 2022 (MC-PILCO), Sec. V-B, with the plateau rule of :mod:`qtl.plateau`.
"""

from __future__ import annotations

import enum
import logging

import torch
from torch import Tensor, nn

from qtl.plateau import PlateauMonitor
from qtl.policy_search.settings import AdamSettings

log = logging.getLogger(__name__)


class Change(enum.Enum):
    """What the schedule makes of a step: nothing, a plateau that annealed it, or a plateau that ends the run."""

    NONE = "none"
    ANNEALED = "annealed"
    STOPPED = "stopped"


def child_generator(generator: torch.Generator | None) -> torch.Generator:
    """A generator seeded from ``generator`` (or torch's global one): the dropout masks' stream."""
    seed = int(torch.randint(2**62, (1,), generator=generator))
    return torch.Generator().manual_seed(seed)


class Schedule:
    """One Adam run's learning rate and dropout: the settings' ``lr`` and ``dropout``, annealed at each plateau.

    At a plateau of the settings' ``plateau`` rule the learning rate is multiplied by ``lr_reduction``
    (not below ``lr_min``) and the dropout lowered by ``dropout_reduction`` (not below 0, fresh masks);
    a plateau at ``lr_min`` stops the run. Without a rule both stay for every step.
    """

    def __init__(self, settings: AdamSettings, policy: nn.Module, generator: torch.Generator | None) -> None:
        self.settings, self.policy, self.generator = settings, policy, generator
        self.lr, self.dropout = settings.lr, settings.dropout  # as annealed so far
        self.monitor: PlateauMonitor | None = None

    def start(self) -> None:
        """Switch the policy's dropout on for the run (masks from a child of the search's generator)."""
        if self.dropout > 0:
            self.policy.set_dropout(self.dropout, child_generator(self.generator))

    def finish(self) -> None:
        """Switch the policy's dropout off after the run (if it was on at the start)."""
        if self.settings.dropout > 0:
            self.policy.set_dropout(0.0)

    def after_step(self, value: Tensor) -> Change:
        """Watch the value V of the step just taken; at a plateau, anneal the learning rate and dropout, or stop."""
        settings = self.settings
        if settings.plateau is None:
            return Change.NONE
        if self.monitor is None:
            self.monitor = PlateauMonitor(settings.plateau, float(value.detach()))
            return Change.NONE
        if not self.monitor.update(float(value.detach())):
            return Change.NONE
        if self.lr <= settings.lr_min:
            log.info("policy search: plateau at lr %.4g after %d steps: stopped", self.lr, self.monitor.step + 1)
            return Change.STOPPED
        self.lr = max(self.lr * settings.lr_reduction, settings.lr_min)
        self.dropout = max(self.dropout - settings.dropout_reduction, 0.0)
        log.info("policy search: plateau after %d steps: lr %.4g, dropout %.3g", self.monitor.step + 1, self.lr,
                 self.dropout)
        self.monitor.annealed()
        self.policy.set_dropout(self.dropout, child_generator(self.generator) if self.dropout > 0 else None)
        return Change.ANNEALED
