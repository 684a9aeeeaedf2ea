"""A finished run's model as its next episode would search on it: the probes' and the particle benchmark's model."""

from __future__ import annotations

from pathlib import Path

from qtl.build import transfer_plan
from qtl.data import TransitionDataset
from qtl.errors import UserError
from qtl.loop import MODEL_STREAM
from qtl.models import DynamicsGP
from qtl.models.warm_start import PreviousFit
from qtl.runs import LoadedRun, load_run
from qtl.seeding import torch_generator


def refitted(run: LoadedRun) -> tuple[TransitionDataset, DynamicsGP]:
    """The run's data, and the model the run's next episode would search on (Algorithm 1, lines 12-13): θ_p fitted
    warm from the checkpoint's fit (``model.warm_start``) with the run's own random stream and the transfer plan's
    cold start, then θ = the updating rule's θ_i from the checkpointed rule state (Eqs. 6-12; θ_p itself for PILCO).
    Loads the run's source run, where it has one."""
    cfg, checkpoint, parts = run.config, run.checkpoint, run.parts
    data = run.dataset()
    plan = transfer_plan(cfg, parts)
    if "transfer" in checkpoint:  # checkpoints of runs made before transfer existed are PILCO runs
        plan.load_state_dict(checkpoint["transfer"])
    generator = torch_generator(cfg.seed, checkpoint["episode"] + 1, MODEL_STREAM)
    model = parts.fit_dynamics(data, generator, start=plan.fit_start(), previous=PreviousFit.of_checkpoint(checkpoint))
    theta_p = model.hyperparameters
    theta = plan.update(theta_p, len(data), plan.compliance(model))
    if theta is not theta_p:
        model.hyperparameters = theta
    return data, model


def loaded(run_dir: Path, checkpoint: Path | None, overrides: list[str]) -> LoadedRun:
    """:func:`qtl.runs.load_run`, bad input (not a run, an unknown override) as a one-line exit."""
    try:
        return load_run(run_dir, checkpoint=checkpoint, overrides=overrides)
    except UserError as err:
        raise SystemExit(f"{run_dir}: {err}") from None
