"""The CLI's helpers: which keys a resumed run may change, the checks made before any work, one-line errors."""

from __future__ import annotations

import io

import pytest
from hydra.errors import MissingConfigException
from omegaconf import OmegaConf

from qtl.checkpoint import latest_checkpoint, load_checkpoint, refuse_existing_run
from qtl.config import check_budget, check_group_keys, run_dir, show_progress
from qtl.errors import CheckpointError, TaskError, UserError
from qtl.loop import run
from qtl.runs import stored_config
from qtl.train import auto_resume, comparable, one_line, resume_config
from tests.helpers import tiny_config


def test_resume_may_change_how_a_run_runs_but_not_what_it_learns(tmp_path):
    run(tiny_config("episodes=0"), tmp_path)
    cfg = resume_config(tmp_path, [f"resume={tmp_path}", "episodes=3", "threads=2", "device=cuda:0",
                                   "kernels.backend=torch", "keep_checkpoints=1"])
    assert (cfg.episodes, cfg.threads, cfg.device, cfg.kernels.backend, cfg.keep_checkpoints, cfg.resume) == (
        3, 2, "cuda:0", "torch", 1, str(tmp_path))
    with pytest.raises(CheckpointError, match="cannot change 'seed'"):
        resume_config(tmp_path, ["seed=4"])
    with pytest.raises(CheckpointError, match="already holds a run's checkpoints"):
        refuse_existing_run(tmp_path)
    refuse_existing_run(tmp_path / "elsewhere")


def test_auto_resume_continues_a_run_whose_config_was_written_the_old_way(tmp_path):
    """A checkpoint's config that lists every env default, the horizon twice and no rule.space is the same run."""
    run(tiny_config("episodes=0"), tmp_path)
    old = OmegaConf.to_container(tiny_config("episodes=0"))
    old["task"]["env"] = {"id": "qtl/CartPoleSwingUp-v0", "pole_mass": 0.5, "friction": 0.1, "horizon": 8}
    old["task"]["horizon"] = "${.env.horizon}"
    del old["rule"]["space"], old["task"]["state_names"]
    checkpoint = load_checkpoint(latest_checkpoint(tmp_path))
    assert comparable(stored_config({"config": OmegaConf.to_yaml(old)})) == comparable(stored_config(checkpoint))
    assert auto_resume(tmp_path, tiny_config("episodes=2")).resume == str(tmp_path)
    with pytest.raises(CheckpointError, match=r"another configuration \(differs: \['seed'\]\)"):
        auto_resume(tmp_path, tiny_config("seed=1"))


def test_kinematics_count_only_where_speed_integration_uses_them():
    """A run stored with task.kinematics null (before the empty default) or without a weight is the same run."""
    stored = OmegaConf.to_container(tiny_config("task=mountaincar"))
    stored["task"]["kinematics"] = None  # as runs made before the mountain car declared its kinematics hold it
    assert comparable(OmegaConf.create(stored)) == comparable(tiny_config("task=mountaincar"))  # delta: inert
    speed = tiny_config("propagation.integration=speed")
    old = OmegaConf.to_container(speed)
    del old["task"]["kinematics"]["weight"]  # a speed run made before task.kinematics.weight: the trapezoid rule
    assert comparable(OmegaConf.create(old)) == comparable(speed)
    assert comparable(speed) != comparable(tiny_config("propagation.integration=speed",
                                                       "task.kinematics.weight=1.0"))


def test_auto_resume_ignores_the_transfer_settings_of_a_run_without_a_source(tmp_path):
    """A PILCO run made when the compliance default was another is the same run; with a source it is not."""
    run(tiny_config("episodes=0"), tmp_path / "pilco")
    old = OmegaConf.to_container(tiny_config("episodes=0"))
    old["transfer"]["compliance"] = "likelihood_ratio"
    del old["transfer"]["compliance_bandwidth"]
    checkpoint = load_checkpoint(latest_checkpoint(tmp_path / "pilco"))
    assert comparable(stored_config({"config": OmegaConf.to_yaml(old)})) == comparable(stored_config(checkpoint))
    run(tiny_config("episodes=1"), tmp_path / "source")
    with_source = [f"transfer.source={tmp_path / 'source'}", "approach=qtl_bayesian", "task.env.pole_mass=2.0"]
    run(tiny_config("episodes=0", *with_source), tmp_path / "qtl")
    with pytest.raises(CheckpointError, match=r"another configuration \(differs: \['transfer'\]\)"):
        auto_resume(tmp_path / "qtl", tiny_config(*with_source, "transfer.compliance=likelihood_ratio"))


@pytest.mark.parametrize(
    ("overrides", "message"),
    [(["episodes=-1"], "episodes=-1: the learned episodes"), (["random_episodes=0"], "random_episodes must be >= 1"),
     (["random_episodes=0", "transfer.policy=true"], "random_episodes must be >= 1"),
     (["keep_checkpoints=-1"], "keep_checkpoints=-1: keep the newest")],
)
def test_budgets_that_cannot_learn_are_refused(overrides, message):
    with pytest.raises(UserError, match=message):
        check_budget(tiny_config(*overrides))
    check_budget(tiny_config("episodes=0"))


def test_resume_runs_in_its_own_directory_and_a_missing_one_is_refused(tmp_path):
    assert run_dir(None, "outputs/x") == "outputs/x" and run_dir("auto", "outputs/x") == "outputs/x"
    assert run_dir(str(tmp_path), "outputs/x") == str(tmp_path)
    with pytest.raises(UserError, match="does not exist"):
        run_dir(str(tmp_path / "nothing"), "outputs/x")


class _Stream(io.StringIO):
    def __init__(self, tty: bool) -> None:
        super().__init__()
        self.tty = tty

    def isatty(self) -> bool:
        return self.tty


def test_progress_bars_follow_the_terminal_unless_set(monkeypatch):
    monkeypatch.setattr("sys.stderr", _Stream(tty=False))
    assert (show_progress(None), show_progress(True)) == (False, True)
    monkeypatch.setattr("sys.stderr", _Stream(tty=True))
    assert (show_progress(None), show_progress(False)) == (True, False)


def test_errors_are_one_line_saying_what_to_fix():
    try:
        try:
            raise TaskError("task.horizon must be a positive number of steps, got 0")
        except TaskError as inner:
            raise RuntimeError("wrapped\nand long") from inner
    except RuntimeError as err:
        assert one_line(err) == "task.horizon must be a positive number of steps, got 0"
    missing = MissingConfigException("In 'train': Could not find 'task/x'\n\nAvailable options...", "task/x",
                                     ["cartpole", "mountaincar"])
    assert one_line(missing) == "In 'train': Could not find 'task/x' (options: cartpole, mountaincar)"


def test_a_key_forced_into_a_group_is_refused():
    check_group_keys(tiny_config())
    with pytest.raises(UserError, match=r"optimizer.restrats is no key of optimizer"):
        check_group_keys(tiny_config("++optimizer.restrats=1"))
