"""TransferPlan: the two seams of Algorithm 1 (ψ_0, θ_i), its checks before any work, its checkpointed state."""

from __future__ import annotations

import csv
import math

import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from qtl.errors import TransferError
from qtl.features import AngleFeatures
from qtl.loop import run
from qtl.models import GPHyperparameters
from qtl.policies import SquashedPolicy
from qtl.task import Task
from qtl.transfer import Bayesian, Forgetting, Free, NoTransfer, SourceRun
from qtl.transfer.compliance import kernel_compliance, task_compliance
from qtl.transfer.plan import TransferPlan, _aligned
from tests.helpers import tiny_config

TASK = Task.from_config(OmegaConf.to_container(tiny_config("task.env.pole_mass=2.0").task, resolve=True))
FEATURES = AngleFeatures(TASK.state_dim, TASK.angle_dims)


def learned(scale: float) -> GPHyperparameters:
    """A θ_p of the task's shape `E x (D + 2)`."""
    rows = torch.full((TASK.state_dim, TASK.gp_input_dim + 2), scale, dtype=torch.float64)
    return GPHyperparameters.from_natural(rows)


def plan(rule, **transfer) -> TransferPlan:
    return TransferPlan(transfer, rule, TASK, FEATURES)


def test_without_a_source_it_is_pilco():
    pilco = plan(NoTransfer())
    assert pilco.describe() == "no transfer (PILCO)" and pilco.source is None and not pilco.transfer_theta
    assert pilco.fit_start() is None and math.isnan(pilco.compliance(None))
    theta_p = learned(0.5)
    assert pilco.update(theta_p, 8) is theta_p


def test_theta_s_first_then_the_rule(finished_source):
    forgetting = plan(Forgetting(gamma=0.5), source=str(finished_source))
    source = SourceRun.load(finished_source)
    assert "θ_s from" in forgetting.describe() and "ψ_s" not in forgetting.describe()
    assert forgetting.fit_start() is None  # evidence maximisation starts from PILCO's heuristic
    first = forgetting.update(learned(0.5), 8)
    torch.testing.assert_close(first.natural(), source.theta.natural(), rtol=0, atol=0)  # θ_0 = θ_s (Eq. 6)
    second = forgetting.update(learned(0.5), 16)
    expected = Forgetting(gamma=0.5).update(first, learned(0.5), 16)  # Eq. 7
    torch.testing.assert_close(second.natural(), expected.natural(), rtol=0, atol=0)
    # The checkpointed state restores θ_{i−1} and the rule's.
    restored = plan(Forgetting(gamma=0.5), source=str(finished_source))
    restored.load_state_dict(forgetting.state_dict())
    torch.testing.assert_close(restored.update(learned(2.0), 24).natural(),
                               forgetting.update(learned(2.0), 24).natural(), rtol=0, atol=0)


def test_free_rule_warm_starts_evidence_maximisation_from_theta_s(finished_source):
    free = plan(Free(), source=str(finished_source))
    assert free.fit_start() is free.source.theta


def test_compliance_gate_drops_theta_s_for_good(finished_source):
    gated = plan(Bayesian(), source=str(finished_source), min_compliance=0.3)
    assert 0.0 <= gated.compliance(gated.source.model(FEATURES)) <= 1.0
    theta_p = learned(0.7)
    assert gated.update(theta_p, 8, compliance=0.1) is theta_p and gated.fallen_back  # at the first model
    assert gated.update(learned(0.9), 16, compliance=0.9).natural().max() == pytest.approx(0.9)
    assert gated.fit_start() is None


def test_compliance_gate_reads_the_first_model_only(finished_source):
    """Later models' Λ, on tuples of the run's own policies, does not move the gate."""
    gated = plan(Bayesian(), source=str(finished_source), min_compliance=0.3)
    first = gated.update(learned(0.5), 8, compliance=0.9)
    assert first is not None and not gated.fallen_back
    theta_p = learned(0.7)
    assert gated.update(theta_p, 16, compliance=0.1) is not theta_p and not gated.fallen_back


def test_transfer_compliance_chooses_the_compliance_the_gate_reads(finished_source):
    """Default: Λ after Lazaric et al. (kernel_compliance, Scott's bandwidth); likelihood_ratio: task_compliance."""
    default = plan(Bayesian(), source=str(finished_source), compliance_resolution=0.1)
    ratio = plan(Bayesian(), source=str(finished_source), compliance="likelihood_ratio", compliance_resolution=0.1)
    exact = plan(Bayesian(), source=str(finished_source), compliance_bandwidth="none")
    source_model = default.source.model(FEATURES)
    target = ratio.source.model(FEATURES)  # the source's own tuples as the target's
    want_kernel = kernel_compliance(source_model, target, resolution=0.1).value
    want_ratio = task_compliance(source_model, target, resolution=0.1).value
    want_exact = kernel_compliance(source_model, target, bandwidth="none").value
    assert default.compliance(target) == pytest.approx(want_kernel, rel=1e-12)
    assert ratio.compliance(target) == pytest.approx(want_ratio, rel=1e-12)
    assert exact.compliance(target) == pytest.approx(want_exact, rel=1e-12)
    assert len({round(v, 9) for v in (want_kernel, want_ratio, want_exact)}) == 3


def test_transferred_policy_is_psi_s(finished_source):
    transfer = plan(NoTransfer(), source=str(finished_source), hyperparameters=False, policy=True)
    draws = TASK.start_distribution().sample(10, generator=torch.Generator().manual_seed(0))
    inner = instantiate(tiny_config().policy)(TASK.feature_dim, TASK.action_dim, start_features=FEATURES(draws))
    made = SquashedPolicy(inner, torch.as_tensor(TASK.action_bound))  # as the loop squashes it
    transfer.initial_policy(made)
    for name, value in transfer.source.policy.items():
        assert torch.equal(made.state_dict()[name], value)


def made_policy() -> SquashedPolicy:
    """PILCO's ψ_0 for the task, made as the loop makes it."""
    draws = TASK.start_distribution().sample(10, generator=torch.Generator().manual_seed(0))
    inner = instantiate(tiny_config().policy)(TASK.feature_dim, TASK.action_dim, start_features=FEATURES(draws))
    return SquashedPolicy(inner, torch.as_tensor(TASK.action_bound))


@pytest.mark.parametrize(("rule", "hyperparameters"), [(Bayesian(), True), (NoTransfer(), False)])
def test_compliance_gate_also_drops_psi_s(finished_source, rule, hyperparameters):
    """A gated run with ψ_s transferred searches from PILCO's ψ_0, with θ_s (QTL) or without (policy transfer)."""
    policy = made_policy()
    pilco_psi = {k: v.clone() for k, v in policy.state_dict().items()}
    gated = plan(rule, source=str(finished_source), hyperparameters=hyperparameters, policy=True, min_compliance=0.3)
    gated.initial_policy(policy)
    assert not torch.equal(policy.state_dict()["policy.targets"], pilco_psi["policy.targets"])  # ψ_s
    theta_p = learned(0.7)
    assert gated.update(theta_p, 8, compliance=0.1, policy=policy) is theta_p and gated.fallen_back
    for name, value in pilco_psi.items():
        assert torch.equal(policy.state_dict()[name], value)


def test_compliance_gate_above_keeps_psi_s(finished_source):
    policy = made_policy()
    kept = plan(Bayesian(), source=str(finished_source), policy=True, min_compliance=0.3)
    kept.initial_policy(policy)
    kept.update(learned(0.7), 8, compliance=0.9, policy=policy)
    assert not kept.fallen_back
    for name, value in kept.source.policy.items():
        assert torch.equal(policy.state_dict()[name], value)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["rule=bayesian"], "rule=bayesian starts from the source's θ_s"),
        (["transfer.policy=true"], "transfer.policy=true needs a source run"),
        (["transfer.min_compliance=0.3"], "transfer.min_compliance needs a source run"),
        (["rule=forgetting", "rule.gamma=1.5"], r"rule.gamma must be in \[0, 1\]"),
    ],
)
def test_bad_transfer_configs_fail_before_any_work(tmp_path, overrides, message):
    with pytest.raises(ValueError, match=message):
        run(tiny_config(*overrides), tmp_path)
    assert not any(tmp_path.iterdir())  # nothing written


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ([], "rule=none ignores θ_s"),
        (["rule=forgetting", "transfer.hyperparameters=false"], "rule=forgetting updates θ_s, but"),
        (["approach=qtl_bayesian", "transfer.min_compliance=1.5"], r"min_compliance must be in \[0, 1\]"),
        (["approach=qtl_bayesian", "transfer.compliance_resolution=-0.1"], "compliance_resolution must be >= 0"),
        (["approach=qtl_bayesian", "transfer.compliance=tip"], "transfer.compliance must be one of"),
        (["approach=qtl_bayesian", "transfer.compliance_bandwidth=silverman"],
         "transfer.compliance_bandwidth must be one of scott, none, got 'silverman'"),
        (["approach=qtl_bayesian", "transfer.compliance=kernel", "transfer.compliance_temperature=2"],
         "tempers the likelihood ratio only"),
        (["approach=policy_transfer", "task.policy_size=4"], "the source policy"),
    ],
)
def test_inconsistent_transfer_with_a_source_fails_before_any_work(finished_source, tmp_path, overrides, message):
    with pytest.raises(TransferError, match=message):
        run(tiny_config(f"transfer.source={finished_source}", *overrides), tmp_path)
    assert not any(tmp_path.iterdir())


def test_theta_is_matched_to_the_models_outputs_by_state_dimension():
    # θ_{i−1} of outputs (0, 1, 3); the model learns (0, 2, 3) (1 found constant, 2 newly varying): θ_{i−1}'s rows
    # of 0 and 3, θ_p's row of 2.
    previous = GPHyperparameters.from_natural(torch.arange(1.0, 13.0, dtype=torch.float64).reshape(3, 4))
    learned = GPHyperparameters.from_natural(torch.full((3, 4), 100.0, dtype=torch.float64))
    aligned = _aligned(previous, (0, 1, 3), learned, (0, 2, 3)).natural()
    torch.testing.assert_close(aligned, torch.stack([previous.natural()[0], learned.natural()[1],
                                                     previous.natural()[2]]), rtol=0, atol=0)
    assert _aligned(previous, (0, 1, 3), learned, (0, 1, 3)) is previous


def test_a_rule_updates_theta_of_the_outputs_the_model_learns(finished_source):
    # The source's θ_s holds all four outputs; a target model that found output 2 constant learns (0, 1, 3).
    rule = Forgetting(gamma=0.5)
    transfer = TransferPlan({"source": str(finished_source)}, rule, TASK, FEATURES)
    theta_s = transfer.source.theta
    learned_3 = GPHyperparameters.from_natural(torch.ones(3, TASK.gp_input_dim + 2, dtype=torch.float64))
    first = transfer.update(learned_3, 10, outputs=(0, 1, 3))
    torch.testing.assert_close(first.natural(), theta_s.natural()[[0, 1, 3]], rtol=0, atol=0)
    assert transfer.state_dict()["theta_outputs"] == [0, 1, 3]
    # Next, every output varies again: output 2 starts from its θ_p, the others follow the rule from θ_{i−1}.
    learned_4 = learned(2.0)
    second = transfer.update(learned_4, 20, outputs=(0, 1, 2, 3))
    assert second.num_outputs == 4
    torch.testing.assert_close(second.natural()[2], learned_4.natural()[2], rtol=1e-12, atol=0)


def test_a_checkpointed_theta_of_every_output_resumes_as_theta_of_the_modelled_outputs():
    # A speed run checkpointed before its GP held only the modelled outputs stored θ of all four.
    speed = TransferPlan({}, NoTransfer(), TASK, FEATURES, outputs=(1, 3))
    full = learned(1.0)
    speed.load_state_dict({"theta": full.state_dict(), "rule": {}, "fallen_back": False})
    torch.testing.assert_close(speed.theta.natural(), full.natural()[[1, 3]], rtol=0, atol=0)
    assert speed.theta_outputs == (1, 3)


# -- several sources: Λ_k of each at the first model chooses θ_s and ψ_s ------------------------------------


def library_plan(source_library, rule=None, **transfer) -> TransferPlan:
    """A plan over the library's two sources (k = 0: 0.5 kg, k = 1: 3 kg), given as the directory that holds them."""
    return plan(Bayesian() if rule is None else rule, source=str(source_library), **transfer)


def test_each_source_gets_its_compliance_and_the_most_compliant_is_chosen(source_library):
    several = library_plan(source_library)
    light, heavy = (SourceRun.load(source_library / name) for name in ("m0.5", "m3.0"))
    assert several.several and several.source is None and several.selected is None
    assert [run.path for run in several.sources] == [light.path, heavy.path]
    assert several.fit_start() is None and several.compliance_columns() == [
        "compliance/0", "compliance/1", "selected_source"]
    target = heavy.model(FEATURES)  # the 3 kg source's own tuples as the target's: it explains them best
    want = [kernel_compliance(run.model(FEATURES), target).value for run in (light, heavy)]
    assert want[1] > want[0]
    assert several.compliance(target) == pytest.approx(want[1], rel=1e-12)  # Λ of the chosen source
    assert several.compliances == pytest.approx(want, rel=1e-12) and several.selected == 1
    assert several.source.path == heavy.path
    assert several.compliance_row() == {"compliance/0": several.compliances[0],
                                        "compliance/1": several.compliances[1], "selected_source": 1}
    first = several.update(learned(0.5), 8, several.compliances[1])
    torch.testing.assert_close(first.natural(), heavy.theta.natural(), rtol=0, atol=0)  # θ_0 = θ_s of the chosen
    # Later models recompute every Λ_k; the choice stays.
    several.compliance(light.model(FEATURES))
    assert several.compliances[0] > several.compliances[1] and several.selected == 1


def test_mixture_theta_s_is_the_compliance_weighted_mean_of_log_theta_s(source_library):
    mixture = library_plan(source_library, rule=Free(), select="mixture")
    light, heavy = (SourceRun.load(source_library / name) for name in ("m0.5", "m3.0"))
    mixture.choose([0.2, 0.6])
    w = (0.2 / 0.8, 0.6 / 0.8)
    by_hand = torch.exp(w[0] * light.theta.natural().log() + w[1] * heavy.theta.natural().log())
    torch.testing.assert_close(mixture.fit_start().natural(), by_hand, rtol=1e-12, atol=0)
    assert mixture.source.path == heavy.path  # ψ_s of the most compliant
    first = mixture.update(learned(0.5), 8, 0.6)
    torch.testing.assert_close(first.natural(), by_hand, rtol=1e-12, atol=0)
    # Every Λ_k 0: equal weights.
    even = library_plan(source_library, select="mixture")
    even.choose([0.0, 0.0])
    torch.testing.assert_close(even.theta_s.natural(), torch.sqrt(light.theta.natural() * heavy.theta.natural()),
                               rtol=1e-12, atol=0)


def test_min_compliance_reads_the_best_source(source_library):
    gated = library_plan(source_library, min_compliance=0.5)
    gated.choose([0.3, 0.4])
    theta_p = learned(0.7)
    assert gated.update(theta_p, 8, compliance=0.4) is theta_p and gated.fallen_back
    kept = library_plan(source_library, min_compliance=0.5)
    kept.choose([0.6, 0.4])
    assert kept.update(learned(0.7), 8, compliance=0.6) is not None and not kept.fallen_back
    assert kept.source.path.name == "m0.5"


def test_psi_s_of_the_chosen_source_once_chosen_and_random_initial_episodes(source_library):
    several = library_plan(source_library, policy=True)
    made = made_policy()
    pilco_psi = {k: v.clone() for k, v in made.state_dict().items()}
    several.initial_policy(made)
    assert several.initial_actor(made) is None  # random actions before the choice
    assert all(torch.equal(made.state_dict()[k], v) for k, v in pilco_psi.items())  # PILCO's ψ_0 until then
    several.choose([0.2, 0.9])
    several.update(learned(0.5), 8, 0.9, made)
    for name, value in several.sources[1].policy.items():
        assert torch.equal(made.state_dict()[name], value)


def test_initial_policy_acts_with_the_named_sources_psi_s(source_library):
    named = library_plan(source_library, initial_policy=str(source_library / "m3.0"))
    made = made_policy()
    named.initial_policy(made)
    acting = named.initial_actor(made)
    assert acting is not made and "initial episodes: ψ_s of" in named.describe()
    for name, value in named.sources[1].policy.items():
        assert torch.equal(acting.state_dict()[name], value)


def test_the_choice_is_checkpointed(source_library):
    mixture = library_plan(source_library, select="mixture")
    mixture.choose([0.7, 0.1])
    mixture.update(learned(0.5), 8, 0.7)
    restored = library_plan(source_library, select="mixture")
    restored.load_state_dict(mixture.state_dict())
    assert restored.selected == 0
    torch.testing.assert_close(restored.theta_s.natural(), mixture.theta_s.natural(), rtol=0, atol=0)


def test_one_source_in_a_list_is_the_single_source_plan(finished_source):
    listed = plan(Bayesian(), source=[str(finished_source)])
    single = plan(Bayesian(), source=str(finished_source))
    assert not listed.several and listed.selected == 0 and listed.describe() == single.describe()
    assert listed.compliance_columns() == [] and listed.state_dict().keys() == single.state_dict().keys()
    target = single.source.model(FEATURES)
    assert listed.compliance(target) == single.compliance(target) and listed.compliance_row() == {}


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["transfer.source=[{light},{missing}]"], "is not a usable source run"),
        (["transfer.source=[{light},{mountaincar}]"], "transfer only works within one family"),
        (["transfer.source={library}", "transfer.initial_policy={missing}"], "is not one of the sources"),
    ],
)
def test_a_bad_source_among_several_fails_before_any_work(source_library, mountaincar_source, tmp_path, overrides,
                                                          message):
    paths = {"light": source_library / "m0.5", "missing": tmp_path / "missing", "library": source_library,
             "mountaincar": mountaincar_source}
    run_dir = tmp_path / "run"
    with pytest.raises(TransferError, match=message):
        run(tiny_config("approach=qtl_bayesian", *(o.format(**paths) for o in overrides)), run_dir)
    assert not run_dir.exists()


@pytest.mark.parametrize(
    "overrides",
    [
        ["rule=none", "transfer.hyperparameters=false", "transfer.policy=true"],
        ["rule=free"],
        ["rule=forgetting", "rule.gamma=0.5"],
        ["approach=qtl_bayesian", "transfer.select=mixture"],
    ],
)
def test_several_sources_run_with_every_rule(source_library, tmp_path, overrides):
    run(tiny_config("episodes=1", "task.env.pole_mass=0.6", f"transfer.source={source_library}", *overrides),
        tmp_path)
    with open(tmp_path / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["kind"] for r in rows] == ["random", "policy"]
    assert rows[1]["selected_source"] == "0" and float(rows[1]["compliance/0"]) > float(rows[1]["compliance/1"])
    assert rows[1]["compliance"] == rows[1]["compliance/0"]


def test_a_resumed_run_of_several_sources_keeps_its_choice(source_library, tmp_path):
    args = ("task.env.pole_mass=0.6", f"transfer.source=[{source_library / 'm3.0'},{source_library / 'm0.5'}]",
            "transfer.select=mixture", "approach=qtl_bayesian")
    run(tiny_config("episodes=1", *args), tmp_path / "resumed")
    run(tiny_config("episodes=2", *args), tmp_path / "resumed", resume=True)
    run(tiny_config("episodes=2", *args), tmp_path / "straight")
    resumed, straight = ((tmp_path / d / "metrics.csv").read_text() for d in ("resumed", "straight"))
    assert resumed == straight and resumed.splitlines()[-1].endswith(",1")  # the 0.5 kg source, listed second
