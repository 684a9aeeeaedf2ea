"""Transfer runs through the loop: θ_s and ψ_s at their seams, the rules in the logs, resume, the gate."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from qtl.build import build
from qtl.checkpoint import latest_checkpoint, load_checkpoint
from qtl.features import AngleFeatures
from qtl.loop import run
from qtl.models import GPHyperparameters
from qtl.task import Task
from qtl.transfer import Bayesian, SourceRun
from tests.helpers import tiny_config

HEAVY = "task.env.pole_mass=2.0"


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def theta_of(row: dict[str, str], prefix: str = "theta") -> torch.Tensor:
    """θ `E x (D + 2)` (natural) from a metrics row."""
    outputs = sorted({k.split("/")[1] for k in row if k.startswith(f"{prefix}/out")}, key=lambda o: int(o[3:]))
    names = [k.split("/", 2)[2] for k in row if k.startswith(f"{prefix}/out0/")]
    return torch.tensor([[float(row[f"{prefix}/{o}/{n}"]) for n in names] for o in outputs], dtype=torch.float64)


@pytest.fixture(scope="module")
def source_dir(tmp_path_factory) -> Path:
    """A finished 0.5 kg source run: one random and two learned episodes."""
    path = tmp_path_factory.mktemp("source")
    run(tiny_config("episodes=2", "seed=3"), path)
    return path


def test_policy_transfer_reproduces_the_source_policy_exactly(source_dir, tmp_path):
    cfg = tiny_config(f"transfer.source={source_dir}", "approach=policy_transfer", HEAVY, "episodes=0", "seed=5")
    run(cfg, tmp_path)
    source = SourceRun.load(source_dir)
    target = load_checkpoint(latest_checkpoint(tmp_path))
    assert read_csv(tmp_path / "metrics.csv")[0]["kind"] == "source_policy"
    for name, value in source.policy.items():
        assert torch.equal(target["policy"][name], value)
    # The target's first episode applied exactly the source policy's actions to its states.
    task = Task.from_config(OmegaConf.to_container(cfg.task, resolve=True))
    features = AngleFeatures(task.state_dim, task.angle_dims)
    policy = build(tiny_config("seed=3")).initial_policy()
    policy.load_state_dict(source.policy)
    states = torch.as_tensor(target["dataset"]["states"][0][:-1])
    with torch.no_grad():  # one observation at a time, as the actor applies it (a batch rounds otherwise)
        expected = torch.stack([policy(features(state)) for state in states])
        expected = expected.clamp(-task.action_bound[0], task.action_bound[0])
    torch.testing.assert_close(torch.as_tensor(target["dataset"]["actions"][0]), expected, rtol=0, atol=0)


def test_theta_transfer_sets_exactly_theta_s_and_nothing_else(source_dir, tmp_path):
    source = SourceRun.load(source_dir)
    keep = tmp_path / "keep"
    run(tiny_config(f"transfer.source={source_dir}", "rule=forgetting", "rule.gamma=1.0", HEAVY, "episodes=2"), keep)
    pilco = tmp_path / "pilco"
    run(tiny_config(HEAVY, "episodes=2"), pilco)
    rows, pilco_rows = read_csv(keep / "metrics.csv"), read_csv(pilco / "metrics.csv")
    assert rows[0] == pilco_rows[0]  # the same random first episode: ψ was not transferred
    for row in rows[1:]:
        torch.testing.assert_close(theta_of(row), source.theta.natural(), rtol=1e-15, atol=0)  # γ = 1 keeps θ_s
        assert not torch.allclose(theta_of(row, "theta_p"), source.theta.natural())  # θ_p is the target's own
    # θ_p is what PILCO learns on the same data: the first learned episode saw the same tuples.
    torch.testing.assert_close(theta_of(rows[1], "theta_p"), theta_of(pilco_rows[1]), rtol=1e-12, atol=0)
    target = load_checkpoint(latest_checkpoint(keep))
    assert len(target["dataset"]["states"]) == 3  # the target's own tuples only
    torch.testing.assert_close(target["theta"]["lengthscales"], source.theta.lengthscales, rtol=1e-15, atol=0)


def test_bayesian_run_logs_theta_p_and_the_fused_theta(source_dir, tmp_path):
    run(tiny_config(f"transfer.source={source_dir}", "approach=qtl_bayesian", HEAVY, "episodes=3"), tmp_path)
    rows = read_csv(tmp_path / "metrics.csv")
    assert [r["kind"] for r in rows] == ["source_policy", "policy", "policy", "policy"]
    source = SourceRun.load(source_dir)
    torch.testing.assert_close(theta_of(rows[1]), source.theta.natural(), rtol=1e-15, atol=0)  # θ_0 = θ_s (Eq. 6)
    rule = Bayesian()  # the preset's defaults
    fused = rule.start(source.theta)
    for episode in (2, 3):  # θ_i from θ_{i−1} and θ_p_i, with n the target tuples before episode i (Eq. 10-12)
        fused = rule.update(fused, GPHyperparameters.from_natural(theta_of(rows[episode], "theta_p")), 8 * episode)
        torch.testing.assert_close(theta_of(rows[episode]), fused.natural(), rtol=1e-12, atol=0)
    compliance = [float(r["compliance"]) for r in rows[1:]]
    assert math.isnan(float(rows[0]["compliance"] or "nan"))
    assert all(0.0 <= c <= 1.0 for c in compliance)
    assert [r["fallback"] for r in rows[1:]] == ["0", "0", "0"]


def test_resumed_transfer_run_equals_an_uninterrupted_one(source_dir, tmp_path):
    overrides = [f"transfer.source={source_dir}", "approach=qtl_bayesian", HEAVY]
    run(tiny_config(*overrides, "episodes=3"), tmp_path / "whole")
    run(tiny_config(*overrides, "episodes=2"), tmp_path / "split")
    run(tiny_config(*overrides, "episodes=3"), tmp_path / "split", resume=True)
    assert read_csv(tmp_path / "whole" / "metrics.csv") == read_csv(tmp_path / "split" / "metrics.csv")


def test_compliance_gate_falls_back_to_pilco(source_dir, tmp_path):
    run(tiny_config(f"transfer.source={source_dir}", "approach=qtl_gamma_09", HEAVY, "episodes=2",
                    "transfer.min_compliance=1.0"), tmp_path)
    rows = read_csv(tmp_path / "metrics.csv")
    assert [r["fallback"] for r in rows[1:]] == ["1", "1"]
    for row in rows[1:]:
        assert float(row["compliance"]) < 1.0
        torch.testing.assert_close(theta_of(row), theta_of(row, "theta_p"), rtol=0, atol=0)
