"""load_run: a run directory read back with its stored config migrated, its checkpoint and its built parts."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from qtl.checkpoint import checkpoint_path, latest_checkpoint, load_checkpoint
from qtl.errors import CheckpointError, UserError
from qtl.loop import run
from qtl.runs import load_run, read_run, stored_config
from tests.helpers import tiny_config

# The engine and fit settings whose defaults changed with issue 18, at the values a run made before then ran with.
BEFORE_THE_FAST_PATHS = ("kernels.backend=torch", "kernels.moments=reference", "model.warm_start=false",
                         "optimizer.batched=false")


def as_made_before_the_fast_paths(run_dir: Path) -> None:
    """Rewrite every checkpoint of ``run_dir`` as a run made before issue 18 stored it: its config without the keys
    that issue added (``kernels``, ``model.warm_start``, ``optimizer.batched``), whose defaults differ today."""
    for path in sorted((run_dir / "checkpoints").glob("episode_*.pt")):
        state = torch.load(path, map_location="cpu", weights_only=True)
        stored = OmegaConf.create(state["config"])
        del stored.kernels, stored.model.warm_start, stored.optimizer.batched
        state["config"] = OmegaConf.to_yaml(stored)
        torch.save(state, path)


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> Path:
    """A finished run: one random and two learned episodes."""
    path = tmp_path_factory.mktemp("finished")
    run(tiny_config("episodes=2", "seed=3"), path)
    return path


def test_load_run_reads_the_newest_checkpoint_its_migrated_config_and_builds_its_parts(finished):
    loaded = load_run(finished)
    state = load_checkpoint(latest_checkpoint(finished))
    assert loaded.episode == state["episode"] == 2 and loaded.path == finished
    assert loaded.config == stored_config(state) and loaded.config == read_run(finished)[0]
    assert loaded.parts.task.name == "cartpole" and loaded.parts.task.horizon == loaded.config.task.horizon
    assert len(loaded.dataset()) == 3 * loaded.parts.task.horizon
    psi = loaded.policy().state_dict()
    assert psi.keys() == state["policy"].keys() and all(torch.equal(psi[k], state["policy"][k]) for k in psi)


def test_load_run_reads_a_chosen_checkpoint_with_overrides(finished):
    loaded = load_run(finished, checkpoint=checkpoint_path(finished, 1),
                      overrides=["propagation=particles", "propagation.num_particles=10", "device=cpu"])
    assert loaded.episode == 1 and len(loaded.dataset()) == 2 * loaded.parts.task.horizon
    assert loaded.config.propagation._target_.endswith("Particles") and loaded.config.propagation.num_particles == 10
    with pytest.raises(UserError, match="unknown override 'nonsense=1'"):
        load_run(finished, overrides=["nonsense=1"])
    with pytest.raises(UserError, match=r"unknown propagation='magic': choose one of \['moment_matching'"):
        load_run(finished, overrides=["propagation=magic"])


def test_a_run_made_before_the_fast_paths_is_rebuilt_as_it_ran_not_with_todays_defaults(tmp_path):
    old = tmp_path / "old"
    run(tiny_config("episodes=1", *BEFORE_THE_FAST_PATHS), old)
    as_made_before_the_fast_paths(old)
    assert "kernels" not in OmegaConf.create(load_checkpoint(latest_checkpoint(old))["config"])
    loaded = load_run(old)
    assert (loaded.config.kernels.backend, loaded.config.kernels.moments) == ("torch", "reference")
    assert loaded.config.model.warm_start is False and loaded.config.optimizer.batched is False
    today = tiny_config()
    assert (today.kernels.backend, today.kernels.moments, today.model.warm_start) == ("auto", "auto", True)


def test_a_directory_that_holds_no_run_is_one_line(tmp_path):
    for where, reason in ((tmp_path / "absent", "does not exist"), (tmp_path, "holds no checkpoints")):
        with pytest.raises(CheckpointError, match=reason) as caught:
            load_run(where)
        assert "\n" not in str(caught.value) and str(where) in str(caught.value)
