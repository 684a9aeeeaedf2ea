"""Reading an experiment directory: cells cut to their common episodes, labels in numeric order."""

from __future__ import annotations

import pytest

from qtl.report import discover, label_order, write_report
from tests.report.fakes import CARTPOLE, make_experiment, write_run


def test_discover_reads_every_cell_cut_to_its_common_episodes(tmp_path):
    experiment = discover(make_experiment(tmp_path, CARTPOLE))
    assert experiment.approaches == ["pilco", "qtl_bayesian"]  # the paper's row order, not the directory's
    assert experiment.labels == ["m1.5", "m2.0"]
    assert sorted(experiment.sources) == [0, 1] and experiment.sources[0].returns == [0.0, 5.0, 9.0, 10.0]
    curves = experiment.curves
    assert curves["pilco"]["m2.0"][1].returns == [0, 10, 10, 10, 16, 16]
    cell = experiment.cell("pilco", "m2.0")
    assert cell is not None and cell.episodes == 6 and cell.truncated and cell.lengths == {0: 6, 1: 8}
    assert not experiment.cell("pilco", "m1.5").truncated
    assert experiment.cell("pilco", "m0.8") is None
    assert experiment.name is None and experiment.commands == [] and experiment.reference is None
    assert [str(p.relative_to(experiment.root)) for p in experiment.run_dirs()][:3] == [
        "target/pilco/m1.5/seed_0", "target/pilco/m1.5/seed_1", "target/pilco/m2.0/seed_0"]


def test_labels_sort_numerically_then_by_name():
    labels = ["helicopter", "m10", "m2.0", "p0.5", "m1.5", "m0.8"]
    assert sorted(labels, key=label_order) == ["m0.8", "m1.5", "m2.0", "m10", "p0.5", "helicopter"]


def test_a_root_without_target_runs_is_an_error(tmp_path):
    with pytest.raises(ValueError, match=f"{tmp_path}: no target runs"):
        write_report(tmp_path)
    write_run(tmp_path / "source" / "seed_0", [1.0, 2.0])
    (tmp_path / "target" / "pilco" / "m1.5" / "seed_0").mkdir(parents=True)  # started, no metrics yet
    with pytest.raises(ValueError, match="no target runs"):
        write_report(tmp_path)
    assert not (tmp_path / "report").exists()
