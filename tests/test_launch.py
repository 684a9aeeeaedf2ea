"""Which overrides make two runs different runs (`qtl.launch.effective`), and the runs a preset's sweep plans
(`qtl.launch.planned_runs`, on the real presets); `ensure_run` itself: test_demo."""

from __future__ import annotations

import pytest
from hydra.core.hydra_config import HydraConfig

from qtl.errors import UserError
from qtl.launch import effective, planned_runs


def test_only_overrides_that_change_what_a_run_learns_count():
    made = ["seed=0", "recipe=mc_pilco", "hydra.run.dir=/x", "progress=false", "threads=1", "episodes=9",
            "resume=auto", "keep_checkpoints=2"]
    assert effective(made) == ["recipe=mc_pilco", "seed=0"]
    assert effective(["seed=1", "resume=auto"]) != effective(["seed=0"])
    assert effective(["task.horizon=100"]) != effective([])
    assert effective(["seed=0", "--", "recipe=mc_pilco"]) == effective(["seed=0", "recipe=mc_pilco"])


def test_full_scale_cartpole_plans_4_targets_x_5_seeds_x_7_approaches(tmp_path):
    runs = planned_runs("cartpole", [f"sweep.root={tmp_path}"])
    assert len(runs) == 4 * 5 * 7
    assert len({r.run_dir for r in runs}) == len(runs)
    # The sweeper's order: seeds outermost, then the pole mass, approaches innermost.
    assert runs[0].run_dir == tmp_path / "target" / "pilco" / "m0.8" / "seed_0"
    assert runs[1].run_dir == tmp_path / "target" / "hyperparameters_transfer" / "m0.8" / "seed_0"
    assert runs[7].run_dir == tmp_path / "target" / "pilco" / "m1.0" / "seed_0"
    assert runs[27].run_dir == tmp_path / "target" / "policy_transfer" / "m2.0" / "seed_0"
    assert runs[28].run_dir == tmp_path / "target" / "pilco" / "m0.8" / "seed_1"
    assert runs[-1].run_dir == tmp_path / "target" / "policy_transfer" / "m2.0" / "seed_4"
    assert runs[0].overrides == ("seed=0", "task.env.pole_mass=0.8", "approach=pilco")
    assert {r.episodes for r in runs} == {25}  # the preset's 24 learned episodes and the initial one


def test_command_line_overrides_narrow_or_replace_the_sweep(tmp_path):
    runs = planned_runs("mountaincar", [f"sweep.root={tmp_path}", "seed=3", "task.env.power=0.5,3.0", "episodes=6"])
    assert [str(r.run_dir.relative_to(tmp_path / "target")) for r in runs] == [
        "pilco/p0.5/seed_3", "qtl_bayesian/p0.5/seed_3", "pilco/p3.0/seed_3", "qtl_bayesian/p3.0/seed_3"]
    assert {r.episodes for r in runs} == {7}


def test_sources_and_one_label_experiments(tmp_path):
    sources = planned_runs("aircraft_source", [f"sweep.root={tmp_path}"])
    assert [r.run_dir for r in sources] == [tmp_path / "source" / f"seed_{s}" for s in range(5)]
    targets = planned_runs("aircraft", [f"sweep.root={tmp_path}"])
    assert {r.run_dir.parent.name for r in targets} == {"helicopter"}


def test_planning_leaves_hydra_global_config_as_it_was(tmp_path):
    assert not HydraConfig.initialized()
    planned_runs("cartpole_quick", [f"sweep.root={tmp_path}"])
    assert not HydraConfig.initialized()


def test_a_preset_that_sweeps_nothing_is_a_clear_error():
    with pytest.raises(UserError, match="sweeps nothing"):
        planned_runs("cartpole_quick", ["hydra.sweeper.params=null"])
