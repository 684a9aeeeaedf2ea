"""What ``qtl-train`` registers and resolves: the ConfigStore entries, ``--help``, the run directory, progress bars."""

from __future__ import annotations

import os
import sys

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from qtl.config.groups import GROUP_SCHEMAS
from qtl.config.help import HELP_TEMPLATE, groups_text, help_text
from qtl.config.schema import TrainConfig
from qtl.errors import UserError

RUN_DIR_RESOLVER = "qtl.run_dir"


def show_progress(setting: bool | None) -> bool:
    """``progress``: as set, or (null) on exactly when stderr is a terminal."""
    return sys.stderr.isatty() if setting is None else bool(setting)


def run_dir(resume: str | None, default: str) -> str:
    """Hydra's run directory: the run being resumed (logs append to its own), else ``default``.

    A ``resume`` directory that does not exist is refused here, before Hydra creates it.
    """
    if resume is None or resume == "auto":
        return default
    path = os.path.abspath(os.path.expanduser(resume))
    if not os.path.isdir(path):
        raise UserError(f"resume={resume!r} does not exist: give the directory of an interrupted run")
    return path


def register_configs() -> None:
    """Register the schema, each group option's schema, the run-directory resolver and the ``--help`` text."""
    store = ConfigStore.instance()
    store.store(name="train_schema", node=TrainConfig)
    for group, options in GROUP_SCHEMAS.items():
        for option, schema in options.items():
            store.store(group=group, name=f"{option}_schema", node=schema)
    # `$` would be read as Hydra's template placeholders and `${` as OmegaConf interpolations.
    keys = help_text().replace("$", "$$").replace("${", "\\${")
    groups = groups_text().replace("$", "$$").replace("${", "\\${")
    store.store(group="hydra/help", name="qtl",
                node={"app_name": "qtl-train", "template": HELP_TEMPLATE.format(keys=keys, groups=groups)})
    if not OmegaConf.has_resolver(RUN_DIR_RESOLVER):
        OmegaConf.register_new_resolver(RUN_DIR_RESOLVER, run_dir)
