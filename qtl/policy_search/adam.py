"""Policy search by Adam (suits stochastic objectives): restarts one after the other, or batched in one Adam."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import ClassVar

import torch
from torch import Tensor, nn

from qtl.policy_search.batch import RestartBatch
from qtl.policy_search.evaluation import checked, state
from qtl.policy_search.keep import snapshot_due
from qtl.policy_search.restarts import RestartingSearch
from qtl.policy_search.schedules import Change, Schedule
from qtl.policy_search.settings import AdamSettings


class AdamSearch(RestartingSearch):
    """Adam for ``steps`` steps per run (suits stochastic objectives); its options are an :class:`AdamSettings`.

    Batched: one Adam over the stacked ψ maximises Σ_r V_r for ``steps`` steps. Adam acts per
    element, so each restart follows the path it follows alone (up to round-off); a restart whose
    value or gradient turns non-finite, or whose rollout fails alone, is dropped at its best ψ and
    the others go on from where they are, their Adam moments kept.

    MC-PILCO's schedule (sequential runs, :class:`~qtl.policy_search.schedules.Schedule`): ``dropout``
    p > 0 drops the policy's basis functions at random during the search
    (:meth:`~qtl.policies.Policy.set_dropout`); with ``plateau`` (a :class:`~qtl.plateau.PlateauRule`)
    a plateau of the objective multiplies the learning rate by ``lr_reduction`` (not below ``lr_min``),
    lowers p by ``dropout_reduction`` and restarts Adam's moments, and a plateau at ``lr_min`` ends the
    run early. ``keep``: ``best`` (the best ψ seen, for a deterministic objective), ``last`` (the final
    ψ, valued by one more evaluation without dropout: the best of many noisy values is biased) or
    ``validated`` (the run's start, ``SNAPSHOTS`` snapshots along the run and the final ψ, each valued
    by one more evaluation without dropout, the best of them: a noisy search can leave a good ψ behind,
    and never leaves a worse one than it began with).
    """

    settings_type: ClassVar[type[AdamSettings]] = AdamSettings
    settings: AdamSettings

    def __init__(self, settings: AdamSettings | None = None) -> None:
        super().__init__(AdamSettings() if settings is None else settings)

    @property
    def batched(self) -> bool:
        """Whether the restarts run batched: as the settings ask, except a scheduled search, which runs sequentially.

        A schedule (``keep`` other than best, dropout, a plateau rule) runs restarts one after the
        other: :class:`AdamSettings` refuses ``batched`` with more than one restart, and with one
        restart the sequential run is the batched one.
        """
        return self.settings.batched and not self.settings.scheduled

    @property
    def keep(self) -> str:
        """Which ψ a run leaves (one of :data:`~qtl.policy_search.keep.KEEP`)."""
        return self.settings.keep

    @property
    def lr_scales(self) -> Mapping[str, float]:
        """The learning rate's factor per part of ψ, by its own name."""
        return self.settings.lr_scales

    def param_groups(self, named: Mapping[str, nn.Parameter], lr: float) -> list[dict]:
        """Adam's parameter groups: each of ψ's parameters at ``lr`` × its ``lr_scales`` factor (1 if unnamed there)."""
        unknown = set(self.lr_scales) - {_short(name) for name in named}
        if unknown:
            raise ValueError(f"optimizer.lr_scales names {sorted(unknown)}, which this policy does not have: "
                             f"choose from {sorted({_short(name) for name in named})}")
        return [{"params": [p], "lr": lr * self.lr_scales.get(_short(name), 1.0)} for name, p in named.items()]

    def _run(self, policy: nn.Module, params: list[nn.Parameter], objective: Callable[[], Tensor],
             tick: Callable[[], None], generator: torch.Generator | None, snapshots: list[dict[str, Tensor]]) -> None:
        settings = self.settings
        schedule = Schedule(settings, policy, generator)
        schedule.start()
        try:
            named = _named(policy, params)
            optimiser = torch.optim.Adam(self.param_groups(named, schedule.lr), lr=schedule.lr)
            for step in range(settings.steps):
                optimiser.zero_grad()
                value = checked(objective())
                (-value).backward()
                optimiser.step()
                tick()
                if snapshot_due(settings.keep, step, settings.steps):
                    snapshots.append(state(policy))
                change = schedule.after_step(value)
                if change is Change.STOPPED:
                    break
                if change is Change.ANNEALED:  # Adam's moments restart at the new learning rate
                    optimiser = torch.optim.Adam(self.param_groups(named, schedule.lr), lr=schedule.lr)
        finally:
            schedule.finish()

    def _run_batched(self, batch: RestartBatch, objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        optimiser = self._optimiser(batch)
        step = 0
        while batch.active and step < self.settings.steps:
            optimiser.zero_grad()
            values, failing = batch.evaluate(objective)
            if not failing:
                (-values.sum()).backward()
                failing = batch.nonfinite_gradients()
            if failing:
                optimiser = self._without(batch, optimiser, failing)
                continue  # the same step again, for the restarts left
            optimiser.step()
            tick()
            step += 1

    def _optimiser(self, batch: RestartBatch) -> torch.optim.Adam:
        """A fresh Adam over the batch's stacked ψ."""
        return torch.optim.Adam(self.param_groups(batch.trainable_named(), self.settings.lr), lr=self.settings.lr)

    def _without(self, batch: RestartBatch, optimiser: torch.optim.Adam, failing: list[int]) -> torch.optim.Adam:
        """Drop the restarts at positions ``failing`` from ``batch``; an Adam over the others, their moments kept."""
        moved = dict(zip(batch.trainable(), [optimiser.state[p] for p in batch.trainable()], strict=True))
        kept = batch.drop(failing)
        optimiser = self._optimiser(batch)
        for old, new in zip(moved, batch.trainable(), strict=True):
            optimiser.state[new] = {
                key: value[kept] if key != "step" and value.dim() > 0 else value for key, value in moved[old].items()
            }
        return optimiser


def _short(name: str) -> str:
    """A parameter's own name, without the modules that hold it (``policy.support_points`` → ``support_points``)."""
    return name.rsplit(".", 1)[-1]


def _named(policy: nn.Module, params: list[nn.Parameter]) -> dict[str, nn.Parameter]:
    """``params`` by their names in ``policy``."""
    ids = {id(p) for p in params}
    return {name: p for name, p in policy.named_parameters() if id(p) in ids}
