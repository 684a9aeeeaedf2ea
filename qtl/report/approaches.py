"""The paper's approaches: one table of the ``configs/approach/`` presets and their names in the paper."""

from __future__ import annotations

# Approach presets (configs/approach/<preset>.yaml) and their names in the paper, in the row order of its tables.
APPROACHES: dict[str, str] = {
    "pilco": "PILCO (γ = 0)",
    "hyperparameters_transfer": "Hyper-parameters transfer",
    "qtl_gamma_09": "QTL-PILCO γ = 0.9",
    "qtl_gamma_05": "QTL-PILCO γ = 0.5",
    "qtl_gamma_1": "QTL-PILCO γ = 1",
    "qtl_bayesian": "QTL-PILCO Bayesian",
    "policy_transfer": "Policy transfer",
}
DEFAULT_APPROACH = "pilco"  # what a run without an `approach=` override is
COMPLIANCE_APPROACH = "qtl_bayesian"  # Table 4 reads this approach's runs where they have compliance


def approach_name(approach: str) -> str:
    """The paper's name of an approach preset (Tables 1-3, 5, 6); an unknown preset keeps its own."""
    return APPROACHES.get(approach, approach)


def approach_order(approach: str) -> tuple[int, str]:
    """Sort key: the paper's row order of Tables 1-3, unknown presets after it by name."""
    known = list(APPROACHES)
    return (known.index(approach), "") if approach in known else (len(known), approach)


def approach_overrides(approach: str) -> list[str]:
    """The ``qtl-train`` overrides that select a preset: none for the default (PILCO), else ``approach=<preset>``."""
    return [] if approach == DEFAULT_APPROACH else [f"approach={approach}"]
