"""The approach table: one entry per ``configs/approach/`` preset, in the paper's row order."""

from __future__ import annotations

from pathlib import Path

from qtl.report import APPROACHES, DEFAULT_APPROACH, approach_name, approach_order, approach_overrides

CONFIGS = Path(__file__).resolve().parents[2] / "configs" / "approach"


def test_the_table_names_exactly_the_approach_presets():
    assert set(APPROACHES) == {p.stem for p in CONFIGS.glob("*.yaml")}
    assert len(APPROACHES) == 7  # the paper's seven
    assert DEFAULT_APPROACH in APPROACHES


def test_names_and_order_follow_the_paper_and_unknown_presets_keep_their_own():
    assert approach_name("qtl_bayesian") == "QTL-PILCO Bayesian"
    assert approach_name("my_preset") == "my_preset"
    presets = ["my_preset", "policy_transfer", "pilco", "a_preset", "qtl_gamma_09"]
    assert sorted(presets, key=approach_order) == ["pilco", "qtl_gamma_09", "policy_transfer", "a_preset",
                                                   "my_preset"]


def test_the_default_needs_no_override():
    assert approach_overrides("pilco") == []
    assert approach_overrides("qtl_gamma_05") == ["approach=qtl_gamma_05"]
