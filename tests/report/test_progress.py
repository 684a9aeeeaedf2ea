"""Where a sweep stands: the runs a preset plans, and what each has made (the real presets, fake run directories)."""

from __future__ import annotations

from pathlib import Path

import pytest
from hydra.core.hydra_config import HydraConfig

from qtl.errors import UserError
from qtl.recorder import TIMINGS_FILE
from qtl.report.progress import PlannedRun, planned_runs, progress_markdown, sweep_progress


def test_full_scale_cartpole_plans_4_targets_x_5_seeds_x_7_approaches(tmp_path):
    runs = planned_runs("cartpole", [f"sweep.root={tmp_path}"])
    assert len(runs) == 4 * 5 * 7
    assert len({r.run_dir for r in runs}) == len(runs)
    # The sweeper's order: pole mass outermost, approaches innermost.
    assert runs[0].run_dir == tmp_path / "target" / "pilco" / "m0.8" / "seed_0"
    assert runs[1].run_dir == tmp_path / "target" / "hyperparameters_transfer" / "m0.8" / "seed_0"
    assert runs[-1].run_dir == tmp_path / "target" / "policy_transfer" / "m2.0" / "seed_4"
    assert runs[0].overrides == ("task.env.pole_mass=0.8", "seed=0", "approach=pilco")
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


def _fake_run(run_dir: Path, episodes: int, seconds: list[float]) -> None:
    (run_dir / "checkpoints").mkdir(parents=True)
    for episode in range(episodes):
        (run_dir / "checkpoints" / f"episode_{episode:04d}.pt").write_bytes(b"")
    rows = ["episode,model_fit_s,policy_search_s,episode_s", *(f"{i},1,2,{s}" for i, s in enumerate(seconds))]
    (run_dir / TIMINGS_FILE).write_text("\n".join(rows) + "\n")


def test_progress_counts_checkpointed_episodes_and_their_recorded_time(tmp_path):
    plan = [PlannedRun(tmp_path / f"seed_{s}", (f"seed={s}",), episodes=3) for s in range(3)]
    _fake_run(plan[0].run_dir, 3, [3600.0, 1800.0, 1800.0])
    _fake_run(plan[1].run_dir, 1, [900.0, 50.0])  # a second episode recorded but not yet checkpointed
    progress = sweep_progress(plan)
    assert [p.done for p in progress] == [3, 1, 0]
    assert [p.finished for p in progress] == [True, False, False]
    assert [p.seconds for p in progress] == [7200.0, 900.0, 0.0]
    text = progress_markdown({"targets": progress}, tmp_path)
    assert "1 of 3 runs finished, 1 begun, 1 not begun; 4 of 9 episodes made (2.2 h recorded)" in text
    assert "| seed_1 | 1 / 3" in text and "not begun" in text
