"""Reading an experiment directory: cells cut to their common episodes, labels in numeric order."""

from __future__ import annotations

import pytest
import yaml

from qtl.report import discover, label_order, write_report
from tests.report.fakes import CARTPOLE, NAN, make_experiment, write_run


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


def test_finished_only_leaves_out_the_runs_short_of_their_configured_episodes(tmp_path):
    # A sweep still running: pilco/m2.0 seed 1 has 8 of 8 episodes, seed 0 only 6 of 8 (and one source is short too).
    root = make_experiment(tmp_path, CARTPOLE)
    for run_dir in [*root.glob("target/*/*/seed_*"), *root.glob("source/seed_*")]:
        (run_dir / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"episodes": 7, "random_episodes": 1}))
    (root / "source" / "seed_0" / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"episodes": 3}))  # 4 of 4
    (root / "source" / "seed_1" / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"episodes": 9}))  # 4 of 10

    everything = discover(root)  # the default: every run, cells cut to their common episodes
    assert everything.cell("pilco", "m2.0").seeds == [0, 1] and everything.left_out == ()

    finished = discover(root, finished_only=True)
    cell = finished.cell("pilco", "m2.0")
    assert cell.seeds == [1] and cell.episodes == 8 and not cell.truncated
    assert finished.cell("pilco", "m1.5") is None  # both of its 6-episode runs are short of 8
    assert sorted(finished.sources) == [0]
    assert finished.left_out == (  # in table order: approaches as the paper's rows, labels, seeds
        "target/pilco/m1.5/seed_0 (6 of 8 episodes)", "target/pilco/m1.5/seed_1 (6 of 8 episodes)",
        "target/pilco/m2.0/seed_0 (6 of 8 episodes)",
        "target/qtl_bayesian/m1.5/seed_0 (6 of 8 episodes)", "target/qtl_bayesian/m1.5/seed_1 (6 of 8 episodes)",
        "target/qtl_bayesian/m2.0/seed_0 (6 of 8 episodes)", "target/qtl_bayesian/m2.0/seed_1 (6 of 8 episodes)",
        "source/seed_1 (4 of 10 episodes)")
    assert finished.approaches == ["pilco"] and finished.labels == ["m2.0"]
    report = write_report(root, tmp_path / "out", finished_only=True).read_text()
    assert "Left out, unfinished" in report and "target/pilco/m2.0/seed_0 (6 of 8 episodes)" in report


def test_finished_only_without_a_finished_target_run_is_an_error(tmp_path):
    root = make_experiment(tmp_path, {"pilco": {"m1.5": {0: ([0, 10, 20], [NAN] * 3)}}})
    (root / "target" / "pilco" / "m1.5" / "seed_0" / ".hydra" / "config.yaml").write_text(
        yaml.safe_dump({"episodes": 24}))
    with pytest.raises(ValueError, match="no finished target runs"):
        write_report(root, finished_only=True)
    assert write_report(root).is_file()  # without the option the run is reported, as it stands
