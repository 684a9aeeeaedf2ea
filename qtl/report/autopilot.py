"""The helicopter's reference line (Section 5.3, Fig. 3): the autopilot's total reward, recorded with the experiment.

The experiment driver (``qtl-experiment``, :mod:`qtl.pipeline.experiment`) flies the autopilot once its runs exist and
stores the result in ``experiment.yaml`` (``reference: {name: autopilot, return: ...}``); the report
only reads it.
"""

from __future__ import annotations

import logging
from pathlib import Path

import gymnasium
from omegaconf import DictConfig, OmegaConf

from qtl.envs import Autopilot
from qtl.report.discover import CONFIG_FILE, Experiment, discover
from qtl.report.record import ExperimentRecord, Reference

logger = logging.getLogger(__name__)

HELICOPTER_ID = "qtl/Helicopter-v0"
AIRCRAFT_EXPERIMENT = "aircraft"
HELICOPTER_LABEL = "helicopter"
AUTOPILOT_NAME = "autopilot"
EnvKwargs = dict[str, float | int | str | bool | list[float]]


def autopilot_return(env_kwargs: EnvKwargs | None = None, seed: int = 0) -> float:
    """Total reward of one helicopter episode flown by the env's :class:`qtl.envs.Autopilot` (the reference of Fig. 3).

    ``env_kwargs`` are ``qtl/Helicopter-v0`` constructor kwargs (an ``id`` key, as in ``task.env``, is ignored).
    """
    kwargs = {key: value for key, value in (env_kwargs or {}).items() if key != "id"}
    env = gymnasium.make(HELICOPTER_ID, **kwargs)
    try:
        pilot = Autopilot(env)
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(pilot(obs))
            total += float(reward)
            done = terminated or truncated
    finally:
        env.close()
    return total


def flies_helicopter(experiment: Experiment) -> bool:
    """Whether the experiment has an autopilot line: an aircraft experiment or a helicopter target (Fig. 3)."""
    return experiment.name == AIRCRAFT_EXPERIMENT or HELICOPTER_LABEL in experiment.labels


def helicopter_kwargs(experiment: Experiment) -> EnvKwargs:
    """`task.env` (with `task.horizon`) of the first target run whose `.hydra/config.yaml` flies the helicopter.

    {} if no run does: the autopilot then flies the env's defaults.
    """
    for run_dir in experiment.run_dirs():
        path = run_dir / CONFIG_FILE
        cfg = OmegaConf.load(path) if path.is_file() else None
        env = None if cfg is None else OmegaConf.select(cfg, "task.env")
        if isinstance(env, DictConfig) and env.get("id") == HELICOPTER_ID:
            kwargs: EnvKwargs = OmegaConf.to_container(env, resolve=True)  # type: ignore[assignment]
            horizon = OmegaConf.select(cfg, "task.horizon")  # the run's episode length, the env's horizon too
            return kwargs if horizon is None else {**kwargs, "horizon": int(horizon)}
    logger.warning("no target run records a %s config: the autopilot flies the default helicopter", HELICOPTER_ID)
    return {}


def record_reference(root: str | Path) -> Reference | None:
    """Fly the autopilot on the experiment's helicopter and store its return in ``experiment.yaml``.

    Returns the reference, or None (and writes nothing) when the experiment does not fly the helicopter.
    """
    experiment = discover(root)
    if not flies_helicopter(experiment):
        return None
    reference = Reference(AUTOPILOT_NAME, autopilot_return(helicopter_kwargs(experiment)))
    ExperimentRecord.read(experiment.root).with_reference(reference).write(experiment.root)
    logger.info("%s: %s return %.2f recorded in experiment.yaml", experiment.root, reference.name, reference.total)
    return reference
