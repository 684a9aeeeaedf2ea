"""Per-cell statistics as DataFrames: mean ± std over seeds (ddof = 1), hand-computed."""

from __future__ import annotations

import math

import pytest

from qtl.report import compliance_table, discover, metric_table
from qtl.report.stats import episode_stats, seed_values
from tests.report.fakes import CARTPOLE, make_experiment


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    return discover(make_experiment(tmp_path_factory.mktemp("stats"), CARTPOLE))


def test_seed_values_hold_each_metric_per_seed_in_table_order(experiment):
    values = seed_values(experiment)
    assert list(values.columns) == ["metric", "approach", "label", "seed", "value"]
    assert len(values) == 3 * 2 * 2 * 2  # metrics x approaches x labels x seeds
    auc = values[values["metric"] == "auc"]
    assert list(auc["approach"].unique()) == ["pilco", "qtl_bayesian"]
    assert auc[(auc["approach"] == "pilco") & (auc["label"] == "m2.0")]["value"].tolist() == [60.0, 54.0]  # cut


def test_metric_table_is_mean_std_ddof1_and_count_per_cell(experiment):
    table = metric_table(experiment, "final_performance")
    assert list(table.columns) == ["mean", "std", "n"]
    assert list(table.index) == [("pilco", "m1.5"), ("pilco", "m2.0"), ("qtl_bayesian", "m1.5"),
                                 ("qtl_bayesian", "m2.0")]
    pilco = table.loc[("pilco", "m1.5")]
    assert pilco["mean"] == 33.0 and pilco["std"] == pytest.approx(math.sqrt(18)) and pilco["n"] == 2  # 30, 36
    assert table.loc[("qtl_bayesian", "m2.0"), "std"] == pytest.approx(math.sqrt(50))  # 20, 30: ddof = 1
    ttc = metric_table(experiment, "time_to_convergence")
    assert ttc.loc[("pilco", "m2.0"), "mean"] == 3.5  # 3 and 4 (the cut run)


def test_compliance_table_prefers_bayesian_and_one_seed_has_no_std(experiment):
    table = compliance_table(experiment)
    assert list(table.index) == ["m1.5", "m2.0"]
    assert table.loc["m1.5", "approach"] == "qtl_bayesian"
    assert table.loc["m1.5", "mean"] == pytest.approx(0.7) and table.loc["m1.5", "std"] == pytest.approx(0.1414213562)
    assert table.loc["m2.0", "approach"] == "pilco" and table.loc["m2.0", "n"] == 1  # only seed 0 at episode 5
    assert math.isnan(table.loc["m2.0", "std"])


def test_episode_stats_are_per_episode_over_seeds(experiment):
    stats = episode_stats(experiment.cell("qtl_bayesian", "m2.0"))  # seeds: 10 20 20 ... / 10 10 30 ...
    assert stats["mean"].tolist() == [10.0, 15.0, 25.0, 25.0, 25.0, 25.0]
    assert stats["std"].tolist() == pytest.approx([0.0, math.sqrt(50), math.sqrt(50), math.sqrt(50), math.sqrt(50),
                                                   math.sqrt(50)])
