"""``qtl-train``: the Hydra entry point — config in, Algorithm 1 run in Hydra's output directory."""

from __future__ import annotations

import logging
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from qtl.checkpoint import latest_checkpoint, load_checkpoint
from qtl.config import TrainConfig, register_configs
from qtl.errors import CheckpointError
from qtl.loop import DTYPES, RunResult, run

log = logging.getLogger(__name__)

# What a resumed run may change of the interrupted run's configuration.
RESUME_OVERRIDABLE = frozenset({"episodes", "progress", "figure_every", "threads", "device", "resume"})


def stored_config(checkpoint: dict) -> DictConfig:
    """A checkpoint's run configuration, checked against (and completed by) the schema."""
    return OmegaConf.merge(OmegaConf.structured(TrainConfig), OmegaConf.create(checkpoint["config"]))


def resume_config(run_dir: Path, overrides: list[str]) -> DictConfig:
    """The interrupted run's configuration, with the few keys a resume may change taken from ``overrides``."""
    cfg = stored_config(load_checkpoint(latest_checkpoint(run_dir)))
    changes = []
    for override in overrides:
        key = override.lstrip("+~").partition("=")[0]
        if key not in RESUME_OVERRIDABLE:
            raise CheckpointError(
                f"cannot change {key!r} when resuming {str(run_dir)!r}: only {sorted(RESUME_OVERRIDABLE - {'resume'})} "
                "may differ from the interrupted run"
            )
        if key != "resume":
            changes.append(override.lstrip("+~"))
    cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(changes))
    cfg.resume = str(run_dir)
    return cfg


def auto_resume(run_dir: Path, cfg: DictConfig) -> DictConfig:
    """``resume=auto`` (sweeps): continue the run in ``run_dir`` if it holds one of this config, else start it.

    A run of another configuration in ``run_dir`` is an error; only the keys a resume may change
    (``episodes``, ``progress``, ``figure_every``, ``threads``, ``device``) may differ, and take ``cfg``'s values.
    """
    try:
        checkpoint = load_checkpoint(latest_checkpoint(run_dir))
    except CheckpointError:
        cfg.resume = None
        return cfg
    stored = stored_config(checkpoint)
    mine = {k: v for k, v in OmegaConf.to_container(cfg).items() if k not in RESUME_OVERRIDABLE}
    theirs = {k: v for k, v in OmegaConf.to_container(stored).items() if k not in RESUME_OVERRIDABLE}
    if mine != theirs:
        differ = sorted(k for k in mine.keys() | theirs.keys() if mine.get(k) != theirs.get(k))
        raise CheckpointError(f"resume=auto: {str(run_dir)!r} holds a run of another configuration (differs: {differ})")
    for key in RESUME_OVERRIDABLE - {"resume"}:
        stored[key] = cfg[key]
    stored.resume = str(run_dir)
    return stored


def summary(result: RunResult) -> str:
    """One line: episodes, final return, success or not."""
    first = result.first_success
    outcome = f"first success at episode {first}" if first is not None else "no successful episode"
    final_ok = "succeeded" if result.successes[-1] else "did not succeed"
    return (
        f"{len(result.returns)} episodes, final return {result.returns[-1]:.2f} ({final_ok}); {outcome}. "
        f"TensorBoard: tensorboard --logdir {result.output_dir}"
    )


register_configs()


@hydra.main(version_base="1.3", config_path="pkg://qtl.configs", config_name="train")
def main(cfg: DictConfig) -> None:
    """Learn the configured task; print where the logs are and a one-line summary."""
    hydra_cfg = HydraConfig.get()
    output_dir = Path(hydra_cfg.runtime.output_dir)
    if cfg.resume == "auto":
        cfg = auto_resume(output_dir, cfg)
    elif cfg.resume is not None:
        output_dir = Path(cfg.resume).expanduser().resolve()
        cfg = resume_config(output_dir, list(hydra_cfg.overrides.task))
        # The resumed episodes are logged into the interrupted run's log too.
        handler = logging.FileHandler(output_dir / f"{hydra_cfg.job.name}.log")
        handler.setFormatter(logging.Formatter("[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"))
        logging.getLogger().addHandler(handler)
    if hydra_cfg.mode == RunMode.MULTIRUN:
        cfg.progress = False
        cfg.threads = cfg.threads or 1
    torch.set_default_dtype(DTYPES[cfg.dtype])
    result = run(cfg, output_dir, resume=cfg.resume is not None)
    line = summary(result)
    log.info(line)
    print(line)


if __name__ == "__main__":
    main()
