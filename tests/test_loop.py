"""The learning loop: a tiny real run, resume equals an uninterrupted run, same seed same metrics."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import DictConfig, OmegaConf

from qtl import health
from qtl.build import build
from qtl.checkpoint import latest_checkpoint, load_checkpoint
from qtl.config import TaskConfig
from qtl.data import TransitionDataset
from qtl.errors import CheckpointError, TaskError
from qtl.gaussian import Gaussian
from qtl.loop import predicted_return, run
from qtl.policy_search import SearchResult
from qtl.propagation import Particles
from qtl.seeding import ENV_STREAM, derive_seed
from qtl.train import resume_config
from tests.helpers import squashed_rbf_parts, tiny_config
from tests.toy_envs import register_spinner, spinner_task


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_tiny_run_leaves_metrics_checkpoints_and_events(tmp_path):
    result = run(tiny_config("episodes=2"), tmp_path)
    rows = read_csv(tmp_path / "metrics.csv")
    assert [r["episode"] for r in rows] == ["0", "1", "2"]
    assert [r["kind"] for r in rows] == ["random", "policy", "policy"]
    assert {"episode", "return", "predicted_return", "success"} <= set(rows[0])
    assert all(float(r["predicted_return"]) >= 0 for r in rows[1:])
    assert float(rows[1]["theta/out0/noise_variance"]) > 0
    assert len(read_csv(tmp_path / "timings.csv")) == 3
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == [
        "episode_0000.pt", "episode_0001.pt", "episode_0002.pt"]
    state = load_checkpoint(latest_checkpoint(tmp_path))
    assert state["episode"] == 2 and len(state["dataset"]["states"]) == 3
    assert state["theta"]["lengthscales"].shape == (4, 6)  # θ per output: E x (features + action)
    assert load_checkpoint(tmp_path / "checkpoints" / "episode_0000.pt")["theta"] is None  # random episode
    assert result.returns == [float(r["return"]) for r in rows]


def test_same_seed_gives_identical_metrics_and_another_seed_does_not(tmp_path):
    run(tiny_config("episodes=1", "seed=3"), tmp_path / "a")
    run(tiny_config("episodes=1", "seed=3"), tmp_path / "b")
    run(tiny_config("episodes=1", "seed=4"), tmp_path / "c")
    a, b, c = ((tmp_path / d / "metrics.csv").read_text() for d in "abc")
    assert a == b
    assert a != c


@pytest.mark.parametrize("model", [
    [],
    ["model.warm_start=true", "model.restarts=2"],  # θ_p (and its objective) of the last fit cross the resume
    ["model.warm_start=true", "model.sparse_above=10", "model.inducing=6"],  # ... and the sparse fit's Z
], ids=["default", "warm", "warm-sparse"])
def test_resume_continues_exactly_as_an_uninterrupted_run(tmp_path, model):
    run(tiny_config("episodes=3", *model), tmp_path / "whole")
    run(tiny_config("episodes=1", *model), tmp_path / "split")  # "interrupted" after episode 1
    run(tiny_config("episodes=3", *model), tmp_path / "split", resume=True)
    whole, split = tmp_path / "whole", tmp_path / "split"
    assert (whole / "metrics.csv").read_text() == (split / "metrics.csv").read_text()
    assert len(read_csv(split / "timings.csv")) == 4
    # health.csv: the same counts, and the episode that began the resumed session marked
    whole_health, split_health = read_csv(whole / "health.csv"), read_csv(split / "health.csv")
    assert [r["resumed"] for r in whole_health] == ["0"] * 4 and [r["resumed"] for r in split_health] == [
        "0", "0", "1", "0"]
    assert [{**r, "resumed": ""} for r in whole_health] == [{**r, "resumed": ""} for r in split_health]
    assert list(whole_health[0]) == ["episode", "resumed", *health.EVENTS]
    a = load_checkpoint(latest_checkpoint(whole))
    b = load_checkpoint(latest_checkpoint(split))
    for sa, sb in zip(a["dataset"]["states"], b["dataset"]["states"], strict=True):
        torch.testing.assert_close(sa, sb, rtol=0, atol=0)
    for name in a["policy"]:
        torch.testing.assert_close(a["policy"][name], b["policy"][name], rtol=0, atol=0)


def test_a_run_keeping_one_checkpoint_resumes_as_a_run_keeping_all(tmp_path, caplog):
    run(tiny_config("episodes=2"), tmp_path / "all")
    run(tiny_config("episodes=1", "keep_checkpoints=1"), tmp_path / "one")
    assert [p.name for p in (tmp_path / "one" / "checkpoints").iterdir()] == ["episode_0001.pt"]
    run(tiny_config("episodes=2", "keep_checkpoints=1"), tmp_path / "one", resume=True)
    assert [p.name for p in (tmp_path / "one" / "checkpoints").iterdir()] == ["episode_0002.pt"]
    assert (tmp_path / "all" / "metrics.csv").read_text() == (tmp_path / "one" / "metrics.csv").read_text()
    with caplog.at_level("INFO", logger="qtl.loop"):  # resuming a finished run: one line and nothing else
        run(tiny_config("episodes=2", "keep_checkpoints=1"), tmp_path / "one", resume=True)
    assert [r.getMessage().split(" ", 1)[1] for r in caplog.records] == [
        "finished already (it holds 3 episodes, the budget is 3): nothing to run"]
    assert (tmp_path / "all" / "metrics.csv").read_text() == (tmp_path / "one" / "metrics.csv").read_text()


def test_resume_from_missing_or_corrupt_directory_is_named(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        run(tiny_config("episodes=1"), tmp_path / "absent", resume=True)
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match="holds no checkpoints"):
        run(tiny_config("episodes=1"), tmp_path / "empty", resume=True)
    (tmp_path / "bad" / "checkpoints").mkdir(parents=True)
    (tmp_path / "bad" / "checkpoints" / "episode_0000.pt").write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="corrupt checkpoint"):
        run(tiny_config("episodes=1"), tmp_path / "bad", resume=True)


@pytest.mark.parametrize(
    ("device", "gpus", "message"),
    [
        ("cuda", 0, "sees no CUDA GPU on this machine"),
        ("cuda:1", 1, "this machine has 1 CUDA device"),
        ("tpu", 0, "not a torch device"),
        ("meta", 0, "qtl runs on cpu or cuda"),
    ],
)
def test_unavailable_device_fails_before_any_work(tmp_path, monkeypatch, device, gpus, message):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: gpus > 0)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: gpus)
    with pytest.raises(ValueError, match=message):
        run(tiny_config(f"device={device}"), tmp_path)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["task.env.id=qtl/NoSuchEnv-v0"], "cannot make task.env.id='qtl/NoSuchEnv-v0'"),
        (["task.horizon=0"], "task.horizon must be a positive number of steps"),
        (["task.env.pole_mass=-1.0"], "bad constructor kwargs .* pole_mass"),
        (["task.angle_dims=[7]"], "task.angle_dims \\[7\\] must be distinct indices below 4"),
    ],
)
def test_bad_task_fails_before_any_work(tmp_path, overrides, message):
    with pytest.raises(TaskError, match=message):
        run(tiny_config(*overrides), tmp_path)
    assert not (tmp_path / "metrics.csv").exists()


def test_above_the_threshold_the_loop_uses_the_sparse_gp(tmp_path, caplog):
    with caplog.at_level("INFO", logger="qtl.models.fitting"):
        result = run(tiny_config("episodes=2", "model.sparse_above=10", "model.inducing=6"), tmp_path)
    assert "16 tuples > model.sparse_above=10: the sparse GP, 6 inducing inputs" in caplog.text
    assert "8 tuples >" not in caplog.text  # the first model (8 tuples) is exact
    assert len(result.returns) == 3 and all(math.isfinite(r) for r in result.predicted_returns[1:])


def whole_and_split_runs(tmp_path: Path) -> tuple[Path, Path, dict]:
    """A tiny 2-episode run, and the same run stopped after 1: its directory, last checkpoint's path and state."""
    run(tiny_config("episodes=2"), tmp_path / "whole")
    split = tmp_path / "split"
    run(tiny_config("episodes=1"), split)
    path = latest_checkpoint(split)
    return split, path, torch.load(path, weights_only=True)


def test_a_run_checkpointed_before_the_model_group_resumes_as_model_auto(tmp_path):
    split, path, state = whole_and_split_runs(tmp_path)
    cfg = OmegaConf.create(state["config"])
    assert cfg.model._target_ == "qtl.models.AutoFit"
    cfg.model = {k: v for k, v in cfg.model.items() if k != "_target_"}  # as runs of the earlier version stored it
    state["config"] = OmegaConf.to_yaml(cfg)
    torch.save(state, path)
    resumed = resume_config(split, ["episodes=2"])
    assert resumed.model._target_ == "qtl.models.AutoFit"
    run(resumed, split, resume=True)
    assert (split / "metrics.csv").read_text() == (tmp_path / "whole" / "metrics.csv").read_text()


def test_predicted_return_is_under_the_task_reward_when_the_search_used_a_wider_one(gp_factory):
    """predicted_return: the search's own value for the task's reward, else a rollout scored by the task's reward."""
    gp, policy, reward = squashed_rbf_parts(gp_factory, 3, (1,), 8, seeds=(22, 23))  # a pendulum's parts
    start = Gaussian(torch.tensor([0.1, 2.5, -0.2], dtype=torch.float64), 0.05 * torch.eye(3, dtype=torch.float64))
    found = SearchResult(value=123.0, evaluations=1, run_values=[123.0], rollouts=1)
    same = Particles(gp, policy, reward, angle_dims=(1,), num_particles=30, seed=6)
    assert predicted_return(same, found, "task", start, 5) == 123.0  # the search valued ψ under the task's reward
    wide = Particles(gp, policy, reward, angle_dims=(1,), num_particles=30, seed=6, reward_width_scale=4.0)
    with torch.no_grad():
        searched = float(wide.expected_return(start, 5))  # the objective: the wider reward
        task_value = float(same.rollout(start, 5).value)  # the same draw (CRN), the task's reward
    got = predicted_return(wide, found, "widened", start, 5)
    assert got == pytest.approx(task_value, rel=1e-12) and got < searched


@pytest.mark.parametrize(("overrides", "name"), [
    ([], "task"),  # moment matching
    (["propagation=particles"], "task"),
    (["propagation=particles", "propagation.reward_width_scale=4.0"], "widened"),
    (["propagation=particles", "propagation.reward_width_scale=4.0", "propagation.reward_task_weight=0.5"],
     "widened+task"),
    (["propagation=particles", "propagation.reward_width_scale=4.0", "propagation.reward_task_weight=1.0"], "task"),
    (["propagation=particles", "propagation.search_cost=auto", "propagation.expected_reward=false"], "search_cost"),
    (["propagation=particles", "propagation.search_cost=auto", "propagation.expected_reward=false",
      "propagation.reward_task_weight=0.5"], "search_cost+task"),  # recipe=mc_pilco's
])
def test_the_search_reward_is_known_by_name(overrides, name):
    """build names what the policy search scores (the tiny cart-pole declares a search cost)."""
    assert build(tiny_config(*overrides)).search_reward == name
def spinner_config(*overrides: str) -> DictConfig:
    """The tiny loop budget on the test spinner: θ wrapped into [−π, π) from θ ≈ π, a short track, no start."""
    cfg = tiny_config(*overrides)
    cfg.task = OmegaConf.merge(OmegaConf.structured(TaskConfig), spinner_task(
        env={"id": register_spinner(), "track": 0.6}, horizon=12, policy_size=5))
    return cfg


def test_a_users_env_with_wrapped_angles_early_ends_and_no_start_distribution_learns_end_to_end(tmp_path, caplog):
    cfg = spinner_config("episodes=2")
    parts = build(cfg)
    first_x0 = parts.task.first_observation(derive_seed(cfg.seed, 0, ENV_STREAM))
    torch.testing.assert_close(parts.start.mean, torch.as_tensor(first_x0), rtol=0, atol=0)  # before any episode
    torch.testing.assert_close(parts.start.cov, torch.diag(torch.full((3,), 0.01**2, dtype=torch.float64)))
    with caplog.at_level("INFO", logger="qtl.loop"):
        result = run(cfg, tmp_path)
    rows = read_csv(tmp_path / "metrics.csv")
    assert [r["kind"] for r in rows] == ["random", "policy", "policy"]
    assert any(int(r["length"]) < 12 for r in rows)  # the cart left the track before the horizon
    assert all(float(r["env_return"]) < 0 <= float(r["return"]) for r in rows)  # the env's reward beside the task's
    assert all(math.isfinite(p) for p in result.predicted_returns[1:])
    # μ_0, Σ_0: none for the random episode, then from the x_0 of the episodes so far, floored at 0.01.
    assert rows[0]["start/mean/0"] == ""
    assert float(rows[1]["start/mean/0"]) == pytest.approx(first_x0[0], abs=1e-12)
    assert [float(rows[1][f"start/std/{i}"]) for i in range(3)] == [0.01] * 3
    assert all(float(rows[2][f"start/std/{i}"]) >= 0.01 for i in range(3))
    assert "estimated from 1 initial state(s)" in caplog.text and "estimated from 2 initial state(s)" in caplog.text
    # The learner's targets: Δθ wrapped into (−π, π] although the env's θ jumped by 2π.
    data = TransitionDataset.from_state(load_checkpoint(latest_checkpoint(tmp_path))["dataset"])
    assert data.angle_dims == (0,)
    raw = np.concatenate([np.diff(data.episode(i)[0][:, 0]) for i in range(data.num_episodes)])
    assert np.abs(raw).max() > math.pi
    delta = data.tensors()[2][:, 0]
    assert bool(((delta > -math.pi) & (delta <= math.pi)).all())


def test_a_run_checkpointed_before_env_return_and_dataset_angles_resumes(tmp_path):
    split, path, state = whole_and_split_runs(tmp_path)
    state["metrics"] = [{k: v for k, v in row.items() if k != "env_return"} for row in state["metrics"]]
    del state["dataset"]["angle_dims"]  # as checkpoints of the earlier version stored them
    torch.save(state, path)
    run(tiny_config("episodes=2"), split, resume=True)
    whole, resumed = read_csv(tmp_path / "whole" / "metrics.csv"), read_csv(split / "metrics.csv")
    assert [r["env_return"] for r in resumed[:2]] == ["", ""] and resumed[2]["env_return"] == whole[2]["env_return"]
    for a, b in zip(whole, resumed, strict=True):
        assert {k: v for k, v in a.items() if k != "env_return"} == {k: v for k, v in b.items() if k != "env_return"}


def test_episodes_that_end_too_early_for_a_model_are_followed_by_more_initial_episodes(tmp_path, caplog):
    """A 0.01 m track: each random episode ends after one step; the first model waits for 3 tuples (a GP's least)."""
    cfg = tiny_config("episodes=3")
    cfg.task = OmegaConf.merge(OmegaConf.structured(TaskConfig), spinner_task(
        env={"id": register_spinner(), "track": 0.01}, horizon=12, policy_size=5))
    with caplog.at_level("INFO", logger="qtl.loop"):
        run(cfg, tmp_path)
    rows = read_csv(tmp_path / "metrics.csv")
    lengths = [int(r["length"]) for r in rows]
    kinds = [r["kind"] for r in rows]
    initial = next(i for i in range(len(rows)) if sum(lengths[: i + 1]) >= 3) + 1  # episodes until 3 tuples
    assert initial > 1 and kinds == ["random"] * initial + ["policy"] * (len(rows) - initial)
    assert "one more initial episode before the first model" in caplog.text
