"""``qtl-train``: the Hydra entry point — config in, checked, Algorithm 1 run in Hydra's output directory.

Bad input (a :class:`~qtl.errors.UserError`, or Hydra's own composition errors such as a typo'd
key) is reported as one line on stderr and in the run's ``train.log``; ``HYDRA_FULL_ERROR=1`` or
``hydra.verbose=...`` shows the traceback instead.
"""

from __future__ import annotations

import copy
import logging
import os
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException, MissingConfigException
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from qtl.build import DTYPES, resolve_device
from qtl.checkpoint import refuse_existing_run, run_lock
from qtl.config import check_budget, check_group_keys, register_configs, show_progress
from qtl.errors import CheckpointError, UserError
from qtl.loop import RunResult, run
from qtl.metrics import first_success
from qtl.runs import read_run
from qtl.task import TRAPEZOID_WEIGHT, declares_kinematics, env_settings

log = logging.getLogger(__name__)

# What a resumed run may change of the interrupted run's configuration.
# Top-level keys: ``kernels`` covers ``kernels.backend`` (the engine, not the maths: round-off only).
RESUME_OVERRIDABLE = frozenset({"episodes", "progress", "figure_every", "threads", "device", "kernels", "video",
                                "keep_checkpoints", "resume"})
HYDRA_DIR = ".hydra"  # the run's record of its configuration, as Hydra lays it out
OMEGACONF_KEY = "full_key:"  # how OmegaConf names the key in the message of an error it re-raises with its own type
FULL_ERROR = "HYDRA_FULL_ERROR"  # Hydra's switch for full tracebacks; qtl-train honours it too


def resume_config(run_dir: Path, overrides: list[str]) -> DictConfig:
    """The interrupted run's configuration, with the few keys a resume may change taken from ``overrides``."""
    cfg, _ = read_run(run_dir)
    changes = []
    for override in overrides:
        key = override.lstrip("+~").partition("=")[0]
        if key.split(".")[0] not in RESUME_OVERRIDABLE:
            raise CheckpointError(
                f"cannot change {key!r} when resuming {str(run_dir)!r}: only {sorted(RESUME_OVERRIDABLE - {'resume'})} "
                "may differ from the interrupted run"
            )
        if key != "resume":
            changes.append(override.lstrip("+~"))
    cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(changes))
    cfg.resume = str(run_dir)
    return cfg


def comparable(cfg: DictConfig) -> dict:
    """What a run computes from: ``cfg`` resolved, less the keys a resume may change, the env's defaults filled in.

    Without a transfer source the rest of the ``transfer`` node is left out: such a run is PILCO whatever it says
    (e.g. a compliance estimate whose default changed since the run was made).
    """
    plain = OmegaConf.to_container(cfg, resolve=True)
    for key in RESUME_OVERRIDABLE:
        plain.pop(key, None)
    plain["task"]["env"] = env_settings(plain["task"])
    if plain.get("transfer", {}).get("source") is None:  # no source: the other transfer keys are inert (PILCO; a
        plain["transfer"] = {"source": None}  # flag that would need one is refused before any work)
    # Kinematics only matter to speed integration; null (older runs) and the empty node both declare none.
    speed = plain.get("propagation", {}).get("integration") == "speed"
    if not (speed and declares_kinematics(plain["task"].get("kinematics"))):
        plain["task"]["kinematics"] = None
    else:  # a run made before task.kinematics.weight integrated by the trapezoid rule
        plain["task"]["kinematics"] = {"weight": TRAPEZOID_WEIGHT, **plain["task"]["kinematics"]}
    return plain


def auto_resume(run_dir: Path, cfg: DictConfig) -> DictConfig:
    """``resume=auto`` (sweeps): continue the run in ``run_dir`` if it holds one of this config, else start it.

    A run of another configuration in ``run_dir`` is an error; only the keys a resume may change
    (``episodes``, ``progress``, ``figure_every``, ``threads``, ``device``, ``kernels``) may differ, and take
    ``cfg``'s values.
    """
    try:
        stored, _ = read_run(run_dir)
    except CheckpointError:
        cfg.resume = None
        return cfg
    mine, theirs = comparable(cfg), comparable(stored)
    if mine != theirs:
        differ = sorted(k for k in mine.keys() | theirs.keys() if mine.get(k) != theirs.get(k))
        raise CheckpointError(f"resume=auto: {str(run_dir)!r} holds a run of another configuration (differs: {differ})")
    for key in RESUME_OVERRIDABLE - {"resume"}:
        stored[key] = cfg[key]
    stored.resume = str(run_dir)
    return stored


def record_config(cfg: DictConfig, output_dir: Path) -> None:
    """What Hydra would write to ``<run>/.hydra/`` (config, Hydra's config, overrides), once the run is accepted."""
    hydra_dir = output_dir / HYDRA_DIR
    hydra_dir.mkdir(parents=True, exist_ok=True)
    (hydra_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg), encoding="utf-8")
    (hydra_dir / "hydra.yaml").write_text(OmegaConf.to_yaml(HydraConfig.instance().cfg), encoding="utf-8")
    overrides = OmegaConf.to_yaml(HydraConfig.get().overrides.task)
    (hydra_dir / "overrides.yaml").write_text(overrides, encoding="utf-8")


def run_directory(cfg: DictConfig) -> Path:
    """The directory the run will work in: the resumed run's (``resume=PATH``), else Hydra's output directory."""
    if cfg.resume is not None and cfg.resume != "auto":
        return Path(cfg.resume).expanduser().resolve()
    return Path(HydraConfig.get().runtime.output_dir)


def prepare(cfg: DictConfig) -> tuple[DictConfig, Path]:
    """The run's configuration and directory, every CLI-level check passed; ``.hydra/`` written for a fresh run."""
    hydra_cfg = HydraConfig.get()
    composed = copy.deepcopy(cfg)
    output_dir = Path(hydra_cfg.runtime.output_dir)
    check_budget(cfg)
    check_group_keys(cfg)
    resolve_device(cfg.device)  # a missing GPU is one line here, before a run directory is written
    if cfg.resume == "auto":
        cfg = auto_resume(output_dir, cfg)
    elif cfg.resume is not None:
        resumed = run_directory(cfg)
        cfg = resume_config(resumed, list(hydra_cfg.overrides.task))
        check_budget(cfg)
        resolve_device(cfg.device)
        if resumed != output_dir.resolve():  # hydra.run.dir elsewhere (a link to it is the same place): log there too
            handler = logging.FileHandler(resumed / f"{hydra_cfg.job.name}.log")
            handler.setFormatter(logging.Formatter("[%(asctime)s][%(name)s][%(levelname)s] - %(message)s"))
            logging.getLogger().addHandler(handler)
        output_dir = resumed
    if cfg.resume is None:
        refuse_existing_run(output_dir)
        record_config(composed, output_dir)
    if hydra_cfg.mode == RunMode.MULTIRUN:
        cfg.progress = False
        cfg.threads = cfg.threads or 1
    else:
        cfg.progress = show_progress(composed.progress)
    return cfg, output_dir


def summary(result: RunResult) -> str:
    """One line: episodes, final return, success or not, the numerical events recovered (``health.csv``)."""
    first = first_success(result.successes)
    outcome = f"first success at episode {first}" if first is not None else "no successful episode"
    final_ok = "succeeded" if result.successes[-1] else "did not succeed"
    return (
        f"{len(result.returns)} episodes, final return {result.returns[-1]:.2f} ({final_ok}); {outcome}; "
        f"{health_summary(result.health)}. TensorBoard: tensorboard --logdir {result.output_dir}"
    )


def health_summary(totals: dict[str, int]) -> str:
    """The run's recovered numerical events in a few words, e.g. ``health: 3 cholesky_jitter (health.csv)``."""
    seen = [f"{n} {event}" for event, n in totals.items() if n]
    return f"health: {', '.join(seen)} (recovered; per episode in health.csv)" if seen else "health: no numerical event"


def one_line(err: BaseException) -> str:
    """What to fix, in one line: a UserError's message (wherever it sits in the chain), or Hydra's error condensed."""
    seen: BaseException | None = err
    while seen is not None:
        if isinstance(seen, UserError):
            return str(seen).splitlines()[0]
        seen = seen.__cause__ or seen.__context__
    first = next((line.strip() for line in str(err).splitlines() if line.strip()), type(err).__name__)
    if isinstance(err, MissingConfigException) and err.options:
        return f"{first} (options: {', '.join(err.options)})"
    cause = err.__cause__
    if isinstance(cause, OmegaConfBaseException) and str(cause).strip():
        return f"{first.rstrip('.')}: {str(cause).splitlines()[0]}"
    if first.endswith(":"):  # e.g. "... ValidationError raised while composing config:": the cause says what
        return f"{first} {_key_and_reason(err)}".rstrip()
    return first


def override_error(err: BaseException) -> str:
    """One line for an error OmegaConf raised with its own type while merging an override: the key, the reason."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    key = next((line.removeprefix(OMEGACONF_KEY).strip() for line in lines if line.startswith(OMEGACONF_KEY)), "?")
    hint = (" (a node that is null in its YAML takes no keys from the command line: give the whole node in a task "
            "YAML of your own, see docs/guide/byo-env.md)" if "NoneType" in lines[0] else "")
    return f"cannot apply the override of {key}: {lines[0]}{hint}"


def _key_and_reason(err: BaseException) -> str:
    """``key: reason`` of the first OmegaConf error in ``err``'s chain (the reason alone without a key; else '')."""
    seen = err.__cause__ or err.__context__
    while seen is not None and not isinstance(seen, OmegaConfBaseException):
        seen = seen.__cause__ or seen.__context__
    if seen is None:
        return ""
    reason = next((line.strip() for line in str(seen).splitlines() if line.strip()), type(seen).__name__)
    key = getattr(seen, "full_key", None)
    return f"{key}: {reason}" if key and str(key) not in reason else reason


def _log_to_files(message: str) -> None:
    """``message`` as an ERROR record in the run's log files only: the console gets it once, on stderr."""
    record = log.makeRecord(log.name, logging.ERROR, __file__, 0, message, None, None)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)


def _wants_traceback(argv: Sequence[str]) -> bool:
    """Whether the user asked for tracebacks: ``HYDRA_FULL_ERROR=1`` or a ``hydra.verbose=...`` override."""
    verbose = any(a.startswith("hydra.verbose=") and a.split("=", 1)[1].lower() not in ("false", "")
                  for a in argv)
    return os.environ.get(FULL_ERROR) == "1" or verbose


register_configs()
# Whether bad input shows its traceback; main() decides before it sets HYDRA_FULL_ERROR for Hydra.
_TRACEBACKS = {"shown": True}


@hydra.main(version_base="1.3", config_path="pkg://qtl.configs", config_name="train")
def train(cfg: DictConfig) -> None:
    """Learn the configured task; print where the logs are and a one-line summary."""
    try:
        with run_lock(run_directory(cfg)):  # one process per run directory, from the first read to the last write
            cfg, output_dir = prepare(cfg)
            torch.set_default_dtype(DTYPES[cfg.dtype])
            result = run(cfg, output_dir, resume=cfg.resume is not None)
    except UserError as err:
        _log_to_files(one_line(err))
        if HydraConfig.get().mode == RunMode.MULTIRUN or _TRACEBACKS["shown"]:
            raise  # the launcher records the failed job and goes on with the others
        sys.stderr.write(f"qtl-train: {one_line(err)}\n")
        raise SystemExit(1) from None
    line = summary(result)
    log.info(line)
    print(line)


def main() -> None:
    """``qtl-train``: Hydra's composition errors and bad input as one line on stderr (exit status 1)."""
    verbose = _TRACEBACKS["shown"] = _wants_traceback(sys.argv)
    # qtl's hydra/launcher/ray preset shares its name with the plugin's schema, which it fills in whole (the
    # plugin's own default includes itself and cannot join a running cluster): Hydra's notice of it is not for users.
    warnings.filterwarnings("ignore", message=r"\s*'hydra/launcher/ray' is validated against ConfigStore schema",
                            category=UserWarning)
    previous = os.environ.get(FULL_ERROR)
    os.environ[FULL_ERROR] = "1"  # Hydra re-raises instead of printing its own multi-line report
    try:
        train()
    except (UserError, HydraException, OmegaConfBaseException) as err:
        if verbose:
            raise
        sys.stderr.write(f"qtl-train: {one_line(err)}\n")
        raise SystemExit(1) from None
    except (AttributeError, KeyError, TypeError, ValueError) as err:
        if verbose or OMEGACONF_KEY not in str(err):
            raise
        sys.stderr.write(f"qtl-train: {override_error(err)}\n")  # an override OmegaConf could not merge
        raise SystemExit(1) from None
    finally:
        if previous is None:
            os.environ.pop(FULL_ERROR, None)
        else:
            os.environ[FULL_ERROR] = previous


if __name__ == "__main__":
    main()
