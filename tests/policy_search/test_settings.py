"""The optimisers' settings: each bad option named; which searches run batched; made from the config by build."""

from __future__ import annotations

import dataclasses

import pytest

from qtl.build import build, build_search
from qtl.errors import UserError
from qtl.plateau import PlateauRule
from qtl.policy_search import AdamSearch, AdamSettings, LBFGSSearch, LBFGSSettings
from tests.helpers import train_config
from tests.policy_search.problems import adam


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="restarts must be >= 1"):
        LBFGSSettings(restarts=0)
    with pytest.raises(ValueError, match="perturbation must be >= 0"):
        AdamSettings(perturbation=-0.1)
    with pytest.raises(ValueError, match="max_iter must be >= 1"):
        LBFGSSettings(max_iter=0)
    with pytest.raises(ValueError, match="steps must be >= 1 and lr > 0"):
        AdamSettings(lr=0.0)


def test_the_defaults_are_the_searches_own():
    assert (LBFGSSearch().restarts, LBFGSSearch().settings.max_iter, LBFGSSearch().batched) == (2, 100, False)
    assert AdamSearch().settings == AdamSettings(steps=300, lr=0.01, restarts=1, perturbation=0.1, batched=False)
    with pytest.raises(dataclasses.FrozenInstanceError):
        AdamSettings().lr = 0.1  # type: ignore[misc]


def test_scheduled_settings_refuse_batched_restarts():
    """A schedule runs restarts one after the other: batched with more is refused; with one, it is sequential."""
    for settings in ({"dropout": 0.25}, {"keep": "last"}, {"plateau": PlateauRule()}):
        with pytest.raises(ValueError, match="restarts one after the other"):
            AdamSettings(restarts=2, batched=True, **settings)
        assert AdamSettings(restarts=1, batched=True, **settings).scheduled
        assert adam(restarts=1, batched=True, **settings).batched is False  # one restart: run sequentially
        assert adam(restarts=2, batched=False, **settings).restarts == 2
    assert adam(restarts=1, batched=True).batched is True  # unscheduled: batched, one restart too


@pytest.mark.parametrize(("settings", "message"), [
    ({"keep": "first"}, "keep must be one of best, last"),
    ({"dropout": 1.0}, r"dropout must be in \[0, 1\)"),
    ({"dropout": -0.1}, r"dropout must be in \[0, 1\)"),
    ({"dropout_reduction": -0.1}, "dropout_reduction >= 0"),
    ({"lr_min": 0.02}, r"lr_min in \[0, lr\]"),
    ({"lr_min": -1e-3}, r"lr_min in \[0, lr\]"),
    ({"lr_reduction": 0.0}, r"lr_reduction must be in \(0, 1\]"),
    ({"lr_reduction": 1.5}, r"lr_reduction must be in \(0, 1\]"),
    ({"lr_scales": {"centres": 0.0}}, "lr_scales must be > 0"),
])
def test_bad_schedule_settings_are_named(settings, message):
    with pytest.raises(ValueError, match=message):
        AdamSettings(lr=0.01, **settings)


def test_a_plateau_rule_given_as_a_mapping_becomes_one():
    plain = AdamSettings(plateau={"ema": 0.9, "threshold": 0.05, "window": 3, "min_steps": 1})
    assert plain.plateau == PlateauRule(0.9, 0.05, 3, 1)
    with pytest.raises(TypeError):
        AdamSettings(plateau={"windw": 3})


@pytest.mark.parametrize(("option", "target"), [("lbfgs", LBFGSSearch), ("adam", AdamSearch)])
def test_config_chooses_batched_restarts(option, target):
    """``optimizer.batched`` is a typed key of both options, true unless set false."""
    assert build_search(train_config(f"optimizer={option}").optimizer).batched is True
    search = build_search(train_config(f"optimizer={option}", "optimizer.batched=false").optimizer)
    assert isinstance(search, target) and search.batched is False


def test_config_keeps_validated():
    search = build_search(train_config("optimizer=adam", "optimizer.keep=validated").optimizer)
    assert isinstance(search, AdamSearch) and search.keep == "validated" and search.batched is False


def test_recipe_mc_pilcos_schedule_reaches_the_settings():
    """``optimizer.plateau`` of recipe=mc_pilco reaches AdamSettings as a mapping and becomes a PlateauRule."""
    search = build_search(train_config("recipe=mc_pilco").optimizer)
    assert isinstance(search, AdamSearch) and search.settings.plateau == PlateauRule(0.99, 0.08, 200, 200)
    settings = search.settings
    assert (settings.keep, settings.dropout, settings.lr, settings.lr_min, search.batched) == (
        "validated", 0.25, 0.01, 0.0025, False)


def test_config_lr_scales_are_checked_against_the_policy_at_build():
    """``optimizer.lr_scales`` reaches AdamSearch; a name the policy lacks is a UserError before any episode."""
    for override in ("+optimizer.lr_scales.support_points=0.05", "++optimizer.lr_scales={support_points:0.05}"):
        assert build(train_config("optimizer=adam", override)).search.lr_scales == {"support_points": 0.05}
    with pytest.raises(UserError, match=r"lr_scales names \['centres'\], which this policy does not have"):
        build(train_config("optimizer=adam", "+optimizer.lr_scales.centres=0.1"))
